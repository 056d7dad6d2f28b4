"""Benchmark the navigation runner's episode loop against raw simulator stepping, timed in the same run.

On one tiny procedural scene (``image2sim.dataengine.procedural`` preset ``tiny``, seed 0) with
point-goal episodes from the planner:

* reference: ``NeuralSimulator.step`` with pre-drawn random actions, no measures (the floor);
* ``run_episode`` with the random agent (measures: geodesic distance field lookup, path length,
  incremental nDTW, ... after every step);
* ``run_episode`` with the oracle follower (adds pure pursuit + line-of-sight checks);
* one distance field (Dijkstra from the goal), paid once per episode.

Reports steps per second (median of several timed runs after a warm-up run) and the ratio against
the reference. Writes ``reports/bench_eval_runner.json`` and ``.md``.
Run: ``.venv/bin/python benchmarks/bench_eval_runner.py [--quick]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess

import numpy as np
from harness import hardware, time_it, write_report
from image2sim.eval.protocols import IMAGE2SIM
from image2sim.eval.runner import (
    AgentSpec,
    NeuralSimBackend,
    embodiment_for,
    episode_seed,
    make_agent,
    run_episode,
    sample_point_goal_episodes,
)

PROTO = dataclasses.replace(IMAGE2SIM, name="bench-tiny", success_distance_m=0.5, ndtw_threshold_m=0.5)


def _timed(fn, warmup: int, runs: int) -> tuple[float, list[float]]:
    """Median seconds of ``fn()`` over ``runs`` calls after ``warmup`` untimed calls."""
    t = time_it(fn, warmup=warmup, repeats=runs)
    return t.wall, list(t.walls)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="Fewer episodes and runs.")
    args = parser.parse_args()
    episodes_n, runs = (4, 3) if args.quick else (12, 5)

    from image2sim.dataengine.procedural import capture_frames, generate_scene, preset
    from image2sim.simulator.navigation import NavGraph, NavMapConfig, extract_navmap
    from image2sim.simulator.sim import NeuralSimulator

    frames, _ = capture_frames(generate_scene(preset("tiny"), seed=0))
    navmap = extract_navmap(frames, embodiment_for(PROTO), NavMapConfig(floor_labels=(1, 10)))
    sim = NeuralSimulator(navmap, NavGraph.build(navmap))
    eps = sample_point_goal_episodes(sim, episodes_n, seed=0, min_distance=1.5)
    backend = NeuralSimBackend(sim, PROTO)

    # Step counts of each runner mode (measured once) so every mode is reported per step.
    def episodes_with(agent_name: str) -> tuple[int, callable]:
        agent = make_agent(AgentSpec(agent_name))

        def go() -> int:
            return sum(
                len(run_episode(backend, agent, e, PROTO, episode_seed(0, e.episode_id))[1]) for e in eps
            )

        return go(), go

    rows = []
    n_random, run_random = episodes_with("random")
    n_oracle, run_oracle = episodes_with("oracle")
    rng = np.random.default_rng(0)
    actions = rng.choice([1, 2, 3], size=max(n_random, n_oracle), p=[0.7, 0.15, 0.15])

    def raw_steps() -> None:
        sim.reset(sim.navmap.map_points[:1], np.zeros(1), observe=False)
        for a in actions[:n_random]:
            sim.step([int(a)], observe=False)

    ref_s, ref_t = _timed(raw_steps, 1, runs)
    ref_rate = n_random / ref_s
    rows.append(("NeuralSimulator.step (reference)", n_random, ref_rate, ref_t))
    for label, n, fn in (
        ("run_episode, random agent", n_random, run_random),
        ("run_episode, oracle agent", n_oracle, run_oracle),
    ):
        med, ts = _timed(fn, 1, runs)
        rows.append((label, n, n / med, ts))
    field_s, field_t = _timed(lambda: sim.planner.distance_field(sim.navmap.map_points[0]), 2, runs * 3)

    commit = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True
    ).stdout.strip()
    result = {
        "benchmark": "eval runner episode loop",
        "hardware": hardware(),
        "load_average": list(os.getloadavg()),
        "git_commit": commit,
        "scene": {"preset": "tiny", "seed": 0, "graph_nodes": int(sim.graph.num_nodes), "episodes": len(eps)},
        "protocol": PROTO.name,
        "runs": runs,
        "warmup": 1,
        "rows": [
            {
                "mode": label,
                "steps": n,
                "steps_per_second": rate,
                "ratio_vs_reference": rate / ref_rate,
                "seconds": ts,
            }
            for label, n, rate, ts in rows
        ],
        "distance_field_seconds": {"median": field_s, "all": field_t},
    }
    load = ", ".join(f"{x:.1f}" for x in result["load_average"])
    nodes = result["scene"]["graph_nodes"]
    lines = [
        "# Navigation runner: episode-loop throughput",
        "",
        f"Hardware: {result['hardware']}; load average {load}; commit {commit}.",
        f"Tiny procedural scene (seed 0, {nodes} graph nodes), {len(eps)} point-goal episodes; "
        f"median of {runs} runs after 1 warm-up run.",
        "",
        "| mode | steps | steps/s | ratio vs reference |",
        "|---|---:|---:|---:|",
    ]
    for r in result["rows"]:
        lines.append(
            f"| {r['mode']} | {r['steps']} | {r['steps_per_second']:.0f} | {r['ratio_vs_reference']:.2f} |"
        )
    lines += [
        "",
        f"One distance field (Dijkstra from the goal, once per episode): {1e3 * field_s:.1f} ms median.",
    ]
    meta = {k: v for k, v in result.items() if k != "rows"}
    write_report("bench_eval_runner", result["rows"], meta, markdown=lines)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
