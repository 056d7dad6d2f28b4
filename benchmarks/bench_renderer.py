"""Benchmark the pixel-flow renderer: one-step vs N-step rendering, and one training step.

Cases (``tiny`` config, 128x256, batch 1, untrained weights: speed does not depend on them):
splat-only (``no_pixel_flow``: no network, the reference floor), 1, 2, 4 and 8 sampler steps, one
step of the preset without its MLP prior path (``decoder.prior_hidden`` 0) and without the whole
prior path (``decoder.prior_filter`` 0, grey prior): their costs, and one MeanFlow training step
(JVP + one-step path + backward). Ratios are against the 4-step sampler measured in the same run
(the issue asks for one step >= 3x faster than four).

Writes ``reports/bench_renderer.json`` and ``.md`` (median of several runs after a warm-up,
hardware string, thread count). Run: ``.venv/bin/python benchmarks/bench_renderer.py [--threads N]``.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable

import torch
from harness import hardware, load_average, time_it, utc_now, write_report
from image2sim.simulator.geometry.cameras import EquirectCamera
from image2sim.simulator.renderer.condition import build_condition
from image2sim.simulator.renderer.config import renderer_config_from_dict, tiny
from image2sim.simulator.renderer.model import PixelFlowRenderer


def hardware_and_load() -> str:
    """The harness hardware string plus the 1-minute load average at start."""
    return f"{hardware()}; 1-min load {load_average():.1f} at start"


def timeit(fn: Callable[[], object], repeats: int) -> tuple[float, list[float], float]:
    """Median wall time (s) of ``repeats`` runs after one warm-up, all wall samples, and the median
    process CPU time (s): on a machine shared with other jobs the wall time also counts waiting for
    a core, the CPU time does not."""
    t = time_it(fn, warmup=1, repeats=repeats)
    return t.wall, list(t.walls), t.cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--threads", type=int, default=1, help="torch threads (1 is fastest on a shared 2-core box)"
    )
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    cfg = tiny()
    h, w = cfg.height, cfg.width
    g = torch.Generator().manual_seed(0)
    cond = build_condition(
        torch.randn(1, 16, h, w, generator=g),
        torch.rand(1, 3, h, w, generator=g),
        torch.rand(1, 1, h, w, generator=g) * 5,
        torch.rand(1, 1, h, w, generator=g),
        EquirectCamera(h, w).ray_map(),
    )
    noise = torch.randn(1, 4, h, w, generator=g)
    model = PixelFlowRenderer(cfg).eval()
    splat = PixelFlowRenderer(renderer_config_from_dict({"ablation": {"no_pixel_flow": True}}, preset="tiny"))
    rows = []
    started = hardware_and_load()
    t_splat, s_splat, c_splat = timeit(lambda: splat.render(cond, noise=noise), args.repeats)
    rows.append(
        {
            "case": "splat-only (no network)",
            "steps": 0,
            "median_s": t_splat,
            "samples_s": s_splat,
            "median_cpu_s": c_splat,
        }
    )
    for steps in (1, 2, 4, 8):
        t, s, c = timeit(lambda steps=steps: model.render(cond, steps=steps, noise=noise), args.repeats)
        rows.append(
            {
                "case": f"pixel flow, {steps} step(s)",
                "steps": steps,
                "median_s": t,
                "samples_s": s,
                "median_cpu_s": c,
            }
        )
    # The preset without its MLP prior path (decoder.prior_hidden), and without the whole prior
    # path (decoder.prior_filter + the hole-filled prior): what each costs per frame, measured beside
    # it.
    for case, decoder in (
        ("pixel flow, 1 step, linear prior filter only (no MLP path)", {"prior_hidden": 0}),
        (
            "pixel flow, 1 step, without the prior path (grey prior)",
            {"prior_filter": 0, "prior_hidden": 0, "prior_fill": "grey"},
        ),
    ):
        variant = PixelFlowRenderer(renderer_config_from_dict({"decoder": decoder}, preset="tiny")).eval()
        t, s, c = timeit(lambda v=variant: v.render(cond, steps=1, noise=noise), args.repeats)
        rows.append({"case": case, "steps": 1, "median_s": t, "samples_s": s, "median_cpu_s": c})
    ref = next(r["median_s"] for r in rows if r["steps"] == 4)
    ref_cpu = next(r["median_cpu_s"] for r in rows if r["steps"] == 4)
    for r in rows:
        r["fps"] = 1.0 / r["median_s"] if r["median_s"] > 0 else float("inf")
        r["speedup_vs_4_steps"] = ref / r["median_s"] if r["median_s"] > 0 else float("inf")
        r["cpu_speedup_vs_4_steps"] = ref_cpu / r["median_cpu_s"] if r["median_cpu_s"] > 0 else float("inf")

    train = PixelFlowRenderer(cfg).train()
    target_rgb, target_depth = torch.rand(2, 3, h, w, generator=g), torch.rand(2, 1, h, w, generator=g) * 5
    cond2, noise2 = cond.expand(2, -1, -1, -1), noise.expand(2, -1, -1, -1)
    r_t, t_t = torch.tensor([0.2, 0.7]), torch.tensor([0.7, 0.7])

    def train_step():
        out = train.losses(cond2, target_rgb, target_depth, noise2, r_t, t_t)
        (out["flow"] + out["rec"]).backward()
        train.zero_grad(set_to_none=True)

    t_train, s_train, c_train = timeit(train_step, max(3, args.repeats // 2))
    result = {
        "benchmark": "renderer",
        "date": utc_now(),
        "hardware": started,
        "config": "tiny (128x256), batch 1 render, batch 2 train step",
        "parameters": sum(p.numel() for p in model.parameters()),
        "reference": "pixel flow, 4 steps",
        "render": rows,
        "train_step_batch2_s": t_train,
        "train_step_samples_s": s_train,
        "train_step_batch2_cpu_s": c_train,
    }
    lines = [
        "# Renderer speed (tiny, 128x256)",
        "",
        f"Hardware: {started}. {result['parameters']:,} parameters. "
        f"Median of {args.repeats} runs after a warm-up; "
        "ratio against the 4-step sampler in the same run.",
        "",
        "| case | median wall (ms) | FPS (wall) | speed-up vs 4 steps (wall) "
        "| median CPU (ms) | speed-up (CPU) |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {1000 * r['median_s']:.1f} | {r['fps']:.1f} | {r['speedup_vs_4_steps']:.2f}x "
            f"| {1000 * r['median_cpu_s']:.1f} | {r['cpu_speedup_vs_4_steps']:.2f}x |"
        )
    lines += [
        "",
        f"One MeanFlow training step (batch 2: JVP + one-step path + backward): {t_train:.2f} s wall, "
        f"{c_train:.2f} s CPU.",
        "",
    ]
    meta = {k: v for k, v in result.items() if k != "render"}
    write_report("bench_renderer", rows, meta, markdown=lines, rows_key="render")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
