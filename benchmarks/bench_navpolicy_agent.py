"""Benchmark Image2Nav streaming inference: KV-cache reuse vs full recomputation, and one BC step.

Writes ``reports/bench_navpolicy_agent.json`` and ``.md``: for the tiny from-scratch policy, the wall
time of a whole episode (median of several runs after one warm-up) with the cache reused between
steps and with the context recomputed at every step (the reference, timed in the same process), and
the time of one behaviour-cloning forward+backward on a 32-observation sample. Both paths are
checked to produce the same actions. Run: ``.venv/bin/python benchmarks/bench_navpolicy_agent.py``.
Numbers depend on machine load; the ratio column is what carries over.
"""

from __future__ import annotations

import copy
from collections.abc import Callable

import numpy as np
import torch
from harness import hardware, time_it, write_report
from image2sim.navpolicy.agent import Image2NavAgent
from image2sim.navpolicy.collate import NavCollator
from image2sim.navpolicy.config import tiny_config
from image2sim.navpolicy.data import make_sample, synthetic_trajectories
from image2sim.navpolicy.model import build_policy
from image2sim.navpolicy.prompting import PromptBuilder

NAME = "bench_navpolicy_agent"


def timeit(fn: Callable[[], object], repeats: int) -> float:
    """Median wall time in seconds of ``repeats`` runs after one warm-up run."""
    return time_it(fn, warmup=1, repeats=repeats).wall


def main(steps: int = 60, repeats: int = 3) -> dict:
    torch.set_num_threads(1)  # tiny models: one thread beats two contended ones
    cfg = tiny_config()
    policy = build_policy(cfg, seed=0)
    frames = synthetic_trajectories(1, steps, steps, seed=3)[0].frames

    def episode(reuse: bool):
        acfg = copy.deepcopy(cfg.agent)
        acfg.reuse_cache = reuse
        agent = Image2NavAgent(policy, acfg, cfg.system_prompt)
        agent.reset("walk to the white wall and stop")
        return [agent.act(f) for f in frames], agent

    a_fast, ag = episode(True)
    a_slow, _ = episode(False)
    if a_fast != a_slow:
        raise SystemExit("streaming and recomputed actions differ: refusing to report timings")
    reused = sum(h.reused_tokens for h in ag.history) / max(1, sum(h.context_tokens for h in ag.history))
    t_fast = timeit(lambda: episode(True), repeats)
    t_slow = timeit(lambda: episode(False), repeats)

    col = NavCollator(
        PromptBuilder(policy.tokenizer, policy.codec, cfg.system_prompt), policy.image_processor
    )
    traj = synthetic_trajectories(1, 100, 100, seed=4)[0]
    batch = col([make_sample(traj, 32, 64, np.random.default_rng(0))])
    model = copy.deepcopy(policy.model).train()

    def bc_step():
        model.zero_grad(set_to_none=True)
        model(**batch).loss.backward()

    t_bc = timeit(bc_step, repeats)
    rows = [
        {
            "case": f"agent episode, {steps} steps, KV-cache reuse",
            "seconds": t_fast,
            "per_step_ms": 1000 * t_fast / steps,
            "ratio_vs_reference": t_slow / t_fast,
        },
        {
            "case": f"agent episode, {steps} steps, recompute (reference)",
            "seconds": t_slow,
            "per_step_ms": 1000 * t_slow / steps,
            "ratio_vs_reference": 1.0,
        },
        {
            "case": f"BC fwd+bwd, 1 sample x 32 obs, {batch['input_ids'].shape[1]} tokens",
            "seconds": t_bc,
            "per_step_ms": 1000 * t_bc,
            "ratio_vs_reference": None,
        },
    ]
    params = sum(p.numel() for p in policy.model.parameters())
    result = {
        "benchmark": NAME,
        "hardware": hardware(),
        "model": f"tiny Qwen3-VL from scratch, {params} parameters, {cfg.observation.height}x"
        f"{cfg.observation.width} observations",
        "repeats": repeats,
        "context_tokens_reused_fraction": reused,
        "rows": rows,
    }
    md = [
        f"# {NAME}",
        "",
        f"Hardware: {result['hardware']}  ",
        f"Model: {result['model']}  ",
        f"Median of {repeats} runs after one warm-up. Streaming and recomputed actions are identical; "
        f"{100 * reused:.0f}% of the context tokens were served from the KV cache.",
        "",
        "| case | seconds | ms / step | speed-up vs recompute |",
        "|---|---:|---:|---:|",
    ]
    for r in rows:
        ratio = "" if r["ratio_vs_reference"] is None else f"{r['ratio_vs_reference']:.2f}x"
        md.append(f"| {r['case']} | {r['seconds']:.3f} | {r['per_step_ms']:.1f} | {ratio} |")
    write_report(NAME, rows, {k: v for k, v in result.items() if k != "rows"}, markdown=md)
    print("\n".join(md))
    return result


if __name__ == "__main__":
    main()
