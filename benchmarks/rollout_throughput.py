"""Rollout throughput: agent-steps per second through ``NeuralSimulator`` with the policy in the loop.

One procedural house (``preset('tiny')``; ``--house-preset default`` for the sim2real pipeline's
house size) is simulated three ways, all with the same navigation map,
graph and kinematics, at the policy's training observation (64x64 pinhole, 90 deg, as in
``configs/navpolicy/tiny-dagger.yaml``; ``--obs`` for other sizes):

* ``exact``: the procedural mesh renderer (the data engine's ground truth, as
  :func:`image2sim.navpolicy.rollout_scenes.procedural_simulator` builds it) -- the reference;
* ``splat_only``: :class:`~image2sim.simulator.sim.GaussianRenderFn` over the house's identity
  Gaussians (``gaussians.build_scene(capture, tiny(), encoder="identity")``), the pinhole view splatted
  directly;
* ``neural``: :class:`~image2sim.simulator.sim.PixelFlowRenderFn` over the same Gaussians, a panorama at
  the renderer's training resolution (tiny: 128x256) in one pixel-flow step, the pinhole view cut from
  it. The renderer is an *untrained* ``PixelFlowRenderer(tiny())`` unless ``--renderer PATH`` gives
  weights (its speed does not depend on them).

B agents step together (B in {1, 4}; ``--batch``), driven by the tiny Image2Nav policy (untrained unless
``--policy``): :class:`~image2sim.navpolicy.agent.Image2NavAgent` (streaming, KV-cache reuse) for B = 1,
:class:`~image2sim.navpolicy.agent.BatchedImage2NavAgent` (one left-padded call, full context) for
B > 1. The loop is the streaming agent's, as the evaluation runner drives it: render B observations,
one policy call gives every agent its next two actions, two ``sim.step`` calls execute them
(``--observe-every 1`` renders and asks the policy at every step instead). An episode is a fixed
number of agent steps from the same starts (``rollout_scenes.sample_tasks``); a STOP does not end it (it is
executed as a no-op step), so every repeat and every renderer does the same amount of work.

Steps/s = B x steps per episode / median episode wall time (median of ``--repeats`` episodes after one
warm-up episode per setting; the settings are timed round-robin, so a change in the shared machine's
load hits all of them alike). The split: render (observations + uint8 conversion), policy (the policy
call) and sim step (kinematics) in ms per agent step; ratios against ``exact`` at the same B, measured
in the same run. Writes ``reports/rollout_throughput.json`` and ``.md``.
Run: ``.venv/bin/python benchmarks/rollout_throughput.py [--quick] [--batch 1 4] [--steps 32]``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import statistics
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from harness import hardware, load_average, time_it, write_report

NAME = "rollout_throughput"
ROWS = ("exact", "splat_only", "neural")
REFERENCE = "exact"
DESCRIPTIONS = {
    "exact": "procedural mesh renderer (exact)",
    "splat_only": "Gaussian splatting only (GaussianRenderFn)",
    "neural": "splat + pixel flow (PixelFlowRenderFn)",
}


@dataclass
class Setting:
    """One timed configuration: a renderer row at a batch size, its simulator and policy driver."""

    row: str
    batch: int
    sim: object
    act: Callable[[list[np.ndarray], list[list[int]] | None], list[list[int]]]
    reset: Callable[[], None]
    agent: str


def build_simulators(
    rows: Sequence[str],
    obs: int,
    hfov: float,
    seed: int,
    work: Path,
    renderer: str | None,
    flow_steps: int,
    backend: str = "auto",
    house_preset: str = "tiny",
    device: str = "cpu",
) -> tuple[dict, dict]:
    """The simulators of ``rows`` on one procedural house (shared navigation map and graph) and a
    description of the scene and renderers."""
    from image2sim.dataengine.procedural import generate_scene, preset, write_scene
    from image2sim.navpolicy.rollout_scenes import procedural_simulator
    from image2sim.simulator.gaussians import build_scene
    from image2sim.simulator.gaussians import tiny as gaussians_tiny
    from image2sim.simulator.renderer.config import tiny as renderer_tiny
    from image2sim.simulator.renderer.model import PixelFlowRenderer
    from image2sim.simulator.sim import NeuralSimulator, ObservationSpec
    from image2sim.simulator.splatting.api import resolve_backend

    t0 = time.perf_counter()
    spec = ObservationSpec(panorama=False, pinhole=True, pinhole_size=obs, pinhole_hfov_deg=hfov)
    exact = procedural_simulator(seed, house_preset)
    exact.spec = spec
    sims: dict = {"exact": exact}
    info: dict = {
        "house": f"procedural preset '{house_preset}', seed {seed}",
        "graph_nodes": len(exact.graph.nodes),
    }
    if {"splat_only", "neural"} & set(rows):
        capture = write_scene(generate_scene(preset(house_preset), seed=seed), work / "capture")
        scene = build_scene(capture, gaussians_tiny(), encoder="identity")
        folder = work / "scene"
        scene.save(folder)
        exact.navmap.save(folder / "navmap.npz")  # the same map and graph: identical kinematics
        exact.graph.save(folder / "navgraph.npz")
        info["gaussians"] = int(scene.manifest()["counts"]["gaussians"])
        info["splat_backend"] = resolve_backend(backend, torch.device(device))
        info["device"] = device
        info["capture_frames"] = int(scene.manifest()["counts"]["frames"])
        if "splat_only" in rows:
            sims["splat_only"] = NeuralSimulator.from_scene(
                folder, observations=spec, backend=backend, device=device
            )
        if "neural" in rows:
            torch.manual_seed(0)
            model = renderer if renderer else PixelFlowRenderer(renderer_tiny())
            sim = NeuralSimulator.from_scene(
                folder, observations=spec, renderer=model, steps=flow_steps, backend=backend, device=device
            )
            net = sim.render_fn.model
            # The renderer is panoramic: it renders at its training resolution, the view is cut from it.
            sim.spec = dataclasses.replace(spec, pano_height=int(net.cfg.height))
            sims["neural"] = sim
            info["neural_renderer"] = {
                "weights": f"weights {renderer}"
                if renderer
                else "untrained PixelFlowRenderer(tiny()) (timing only)",
                "panorama": f"{net.cfg.height}x{2 * net.cfg.height}",
                "flow_steps": flow_steps,
                "parameters": sum(p.numel() for p in net.parameters()),
            }
    info["setup_s"] = time.perf_counter() - t0
    return {r: sims[r] for r in rows}, info


def build_policy_driver(policy_config: str, policy: str | None, obs: int):
    """The navigation policy (tiny Image2Nav) and its config, with the observation size set."""
    from image2sim.navpolicy.config import load_config
    from image2sim.navpolicy.model import build_policy

    overrides: dict = {"observation": {"height": obs, "width": obs}}
    if policy:
        overrides["model"] = {"source": str(policy)}
    cfg = load_config(policy_config, overrides)
    net = build_policy(cfg, seed=cfg.train.seed)
    net.model.eval()
    return net, cfg


def make_driver(net, cfg, batch: int, instructions: list[str]):
    """``(act, reset, name)``: ``act(rgbs, executed)`` gives every agent its next actions."""
    from image2sim.navpolicy.agent import BatchedImage2NavAgent, Image2NavAgent

    if batch == 1:
        agent = Image2NavAgent(net, cfg.agent, cfg.system_prompt)

        def act(rgbs, executed):
            return [[int(a) for a in agent.act(rgbs[0], executed=None if executed is None else executed[0])]]

        def reset():
            agent.reset(instructions[0])

        return act, reset, "Image2NavAgent (streaming, KV-cache reuse)"
    batched = BatchedImage2NavAgent(net, cfg.agent, cfg.system_prompt, batch)

    def act_b(rgbs, executed):
        return [[int(a) for a in acts] for acts in batched.act(rgbs, executed=executed)]

    def reset_b():
        for i in range(batch):
            batched.reset(i, instructions[i])

    return act_b, reset_b, f"BatchedImage2NavAgent x{batch} (full context per call)"


def _uint8(rgb: np.ndarray) -> np.ndarray:
    return np.clip(np.asarray(rgb, np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def episode(s: Setting, starts: np.ndarray, headings: np.ndarray, steps: int, every: int) -> dict:
    """One fixed-length episode of ``s.batch`` agents; returns the time spent in each phase."""
    clock = time.perf_counter
    phases = {"render_s": 0.0, "policy_s": 0.0, "sim_s": 0.0}
    actions: collections.Counter = collections.Counter()
    sim = s.sim
    sim.reset(starts[: s.batch], headings[: s.batch], observe=False)
    s.reset()
    executed: list[list[int]] | None = None
    done = 0
    while done < steps:
        t0 = clock()
        rgbs = [_uint8(o["pinhole"]["rgb"]) for o in sim.observe_all()]
        t1 = clock()
        acts = s.act(rgbs, executed)
        t2 = clock()
        n = min(every, steps - done)
        for j in range(n):
            chosen = [a[j] for a in acts]
            actions.update(chosen)
            sim.step(chosen, observe=False)
        t3 = clock()
        executed = [a[:n] for a in acts]
        done += n
        phases["render_s"] += t1 - t0
        phases["policy_s"] += t2 - t1
        phases["sim_s"] += t3 - t2
    phases["actions"] = dict(actions)
    return phases


def run(
    *,
    batches: Sequence[int] = (1, 4),
    steps: int = 32,
    repeats: int = 5,
    obs: int = 64,
    rows: Sequence[str] = ROWS,
    renderer: str | None = None,
    flow_steps: int = 1,
    policy: str | None = None,
    policy_config: str = "tiny",
    observe_every: int = 2,
    seed: int = 0,
    threads: int = 1,
    backend: str = "auto",
    house_preset: str = "tiny",
    device: str = "cpu",
) -> tuple[list[dict], dict, list[str]]:
    """Measure every (row, batch) setting; returns the rows, the report metadata and its Markdown."""
    from image2sim.navpolicy.rollout_scenes import sample_tasks
    from image2sim.simulator.conventions import Action

    if REFERENCE not in rows:
        raise ValueError(f"rows must include the reference {REFERENCE!r}, got {list(rows)}")
    if observe_every not in (1, 2):
        raise ValueError(f"observe_every must be 1 or 2, got {observe_every}")
    if steps < 1 or repeats < 1 or min(batches) < 1:
        raise ValueError("steps, repeats and every batch size must be >= 1")
    torch.set_num_threads(threads)
    # transformers warns at every batched call that Qwen3-VL's past_key_values argument is renamed.
    warnings.filterwarnings("ignore", message=".*past_key_values.*deprecated", category=FutureWarning)
    load_start = load_average()
    hw = hardware()
    if torch.device(device).type == "cuda":
        hw += f"; Gaussian rows on {torch.cuda.get_device_name(torch.device(device))}"
    rows = [r for r in ROWS if r in rows]
    batches = sorted(set(int(b) for b in batches))
    with tempfile.TemporaryDirectory(prefix="bench_rollout_") as tmp:
        net, cfg = build_policy_driver(policy_config, policy, obs)
        if cfg.observation.camera != "pinhole":
            raise ValueError(
                f"the policy's camera is {cfg.observation.camera!r}: only pinhole is benchmarked"
            )
        hfov = float(cfg.observation.hfov_deg)
        sims, scene_info = build_simulators(
            rows, obs, hfov, seed, Path(tmp), renderer, flow_steps, backend, house_preset, device
        )
        tasks = sample_tasks(sims[REFERENCE], max(batches), np.random.default_rng(seed), scene_id="bench")
        starts = np.stack([t.start for t in tasks])
        headings = np.array([t.heading for t in tasks])
        settings = []
        for b in batches:
            for r in rows:
                act, reset, agent = make_driver(net, cfg, b, [t.instruction for t in tasks])
                settings.append(Setting(r, b, sims[r], act, reset, agent))
        records: dict[tuple[str, int], list[dict]] = {(s.row, s.batch): [] for s in settings}

        def timed(s: Setting) -> dict:
            out: dict = {}
            t = time_it(
                lambda: out.update(episode(s, starts, headings, steps, observe_every)), warmup=0, repeats=1
            )
            return {**out, "wall_s": t.wall, "cpu_s": t.cpu}

        for s in settings:  # warm-up: kernels, allocator, tokenizer caches (not timed)
            timed(s)
        for _ in range(repeats):  # round-robin: load changes hit every setting alike
            for s in settings:
                records[(s.row, s.batch)].append(timed(s))
    load_end = load_average()

    out_rows = []
    for s in settings:
        rec = records[(s.row, s.batch)]
        n = s.batch * steps
        wall = statistics.median(r["wall_s"] for r in rec)
        cpu = statistics.median(r["cpu_s"] for r in rec)
        split = {
            k: 1000 * statistics.median(r[f"{k}_s"] for r in rec) / n for k in ("render", "policy", "sim")
        }
        acts = collections.Counter()
        for r in rec:
            acts.update(r["actions"])
        out_rows.append(
            {
                "renderer": s.row,
                "batch": s.batch,
                "agent": s.agent,
                "agent_steps_per_episode": n,
                "steps_per_s": n / wall,
                "steps_per_cpu_s": n / cpu,
                "render_ms_per_step": split["render"],
                "render_ms_per_observation": split["render"] * observe_every,
                "policy_ms_per_step": split["policy"],
                "sim_step_ms_per_step": split["sim"],
                "other_ms_per_step": 1000
                * statistics.median(r["wall_s"] - r["render_s"] - r["policy_s"] - r["sim_s"] for r in rec)
                / n,
                "median_episode_s": wall,
                "median_episode_cpu_s": cpu,
                "episodes_s": [round(r["wall_s"], 4) for r in rec],
                "action_fractions": {
                    Action(int(a)).name: round(c / sum(acts.values()), 3) for a, c in sorted(acts.items())
                },
            }
        )
    ratios: dict = {}
    for r in out_rows:
        ref = next(x for x in out_rows if x["renderer"] == REFERENCE and x["batch"] == r["batch"])
        r["speed_vs_exact"] = r["steps_per_s"] / ref["steps_per_s"]
        r["cpu_speed_vs_exact"] = r["steps_per_cpu_s"] / ref["steps_per_cpu_s"]
        r["render_speed_vs_exact"] = ref["render_ms_per_step"] / r["render_ms_per_step"]
        if r["renderer"] != REFERENCE:
            ratios.setdefault(f"{r['renderer']}/{REFERENCE}", {})[f"B={r['batch']}"] = r["speed_vs_exact"]

    meta = {
        "hardware": hw,
        "load_average_start": load_start,
        "load_average_end": load_end,
        "threads": threads,
        "statistic": f"median of {repeats} episodes after one warm-up episode per setting (round-robin)",
        "observation": f"{obs}x{obs} pinhole, {hfov:g} deg",
        "steps_per_episode": steps,
        "observe_every": observe_every,
        "batches": batches,
        "reference": REFERENCE,
        "scene": scene_info,
        "policy": {
            "config": policy_config,
            "weights": f"Image2Nav weights {policy}"
            if policy
            else "untrained tiny Image2Nav (build_policy, timing only)",
            "parameters": sum(p.numel() for p in net.model.parameters()),
            "context_frames": f"{cfg.agent.sparse_frames} sparse + {cfg.agent.dense_frames} dense",
        },
        "ratios_steps_per_s": ratios,
    }
    return out_rows, meta, markdown(out_rows, meta)


def markdown(rows: list[dict], meta: dict) -> list[str]:
    """The report's Markdown: settings, the table and how to read it."""
    sc, pol = meta["scene"], meta["policy"]
    nr = sc.get("neural_renderer")
    every = meta["observe_every"]
    loop = (
        "render B observations, one policy call (two actions per agent), two `sim.step` calls"
        if every == 2
        else "render B observations, one policy call, one `sim.step` call (the first action)"
    )
    gaussians = (
        f", {sc['gaussians']:,} identity Gaussians from {sc['capture_frames']} panoramas, splatting "
        f"backend `{sc['splat_backend']}`"
        if "gaussians" in sc
        else ""
    )
    ratios = ", ".join(
        f"{k}: " + ", ".join(f"{b} {v:.2f}x" for b, v in d.items())
        for k, d in meta["ratios_steps_per_s"].items()
    )
    fractions = {json.dumps(r["action_fractions"], sort_keys=True) for r in rows}
    if len(fractions) == 1:
        actions = ", ".join(f"{k} {v:.0%}" for k, v in rows[0]["action_fractions"].items()) + " (every row)"
    else:
        actions = "; ".join(
            f"{r['renderer']} B={r['batch']}: "
            + ", ".join(f"{k} {v:.0%}" for k, v in r["action_fractions"].items())
            for r in rows
        )
    present = [f"`{k}` = {v}" for k, v in DESCRIPTIONS.items() if any(r["renderer"] == k for r in rows)]
    lines = [
        "# Rollout throughput: NeuralSimulator + policy",
        "",
        f"Hardware: {meta['hardware']}; 1-min load average {meta['load_average_start']:.1f} at start, "
        f"{meta['load_average_end']:.1f} at the end.  ",
        f"House: {sc['house']} ({sc['graph_nodes']} graph nodes{gaussians}). "
        f"Observation: {meta['observation']} (the policy's training observation).  ",
        f"Policy: {pol['weights']}, {pol['parameters']:,} parameters, context "
        f"{pol['context_frames']} frames, config `{pol['config']}`.  ",
    ]
    if nr:
        lines.append(
            f"Neural renderer: {nr['weights']}, {nr['parameters']:,} parameters, {nr['panorama']} panorama "
            f"in {nr['flow_steps']} step(s), pinhole view cut from it.  "
        )
    lines += [
        f"Loop per observation: {loop}. Episodes of {meta['steps_per_episode']} agent steps from fixed "
        "starts (STOP executed as a no-op, episodes never end early). "
        f"{meta['statistic'].capitalize()}; ratios against the exact renderer at the same B, same run.",
        "",
        "| renderer | B | steps/s | vs exact | render ms/step | policy ms/step | sim step ms/step "
        "| other ms/step | steps/CPU-s | render speed vs exact |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        cells = [
            r["renderer"],
            str(r["batch"]),
            f"{r['steps_per_s']:.1f}",
            f"{r['speed_vs_exact']:.2f}x",
            f"{r['render_ms_per_step']:.2f}",
            f"{r['policy_ms_per_step']:.2f}",
            f"{r['sim_step_ms_per_step']:.3f}",
            f"{r['other_ms_per_step']:.3f}",
            f"{r['steps_per_cpu_s']:.1f}",
            f"{r['render_speed_vs_exact']:.2f}x",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    lines += [
        "",
        "Steps/s = agent steps (B agents x steps) per wall second; ms/step = time of the phase per agent "
        f"step (one observation per {every} step(s)); steps/CPU-s uses the process CPU time instead of "
        "the wall time. B = 1 uses the streaming agent (KV cache reused between calls), B > 1 the "
        "batched agent, which re-runs every agent's full context at each call, so its policy time grows "
        "along the episode." + (f" Steps/s ratios: {ratios}." if ratios else ""),
        "",
        f"Actions executed: {actions}.",
        "",
        f"Rows: {'; '.join(present)}. The untrained weights time the same computation as trained ones; "
        "`--renderer` / `--policy` time given weights. "
        "Run: `.venv/bin/python benchmarks/rollout_throughput.py`.",
    ]
    return lines


def main(argv: Sequence[str] | None = None, reports: str | Path | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, nargs="+", help="agents stepping together (default 1 4)")
    ap.add_argument("--steps", type=int, help="agent steps per episode (default 32)")
    ap.add_argument("--repeats", type=int, help="timed episodes per setting, median (default 5)")
    ap.add_argument("--obs", type=int, default=64, help="policy observation size (square pinhole)")
    ap.add_argument("--rows", nargs="+", choices=ROWS, default=list(ROWS), help="renderers (exact always)")
    ap.add_argument("--renderer", default=None, help="trained pixel-flow weights (.safetensors / .ckpt)")
    ap.add_argument("--flow-steps", type=int, default=1, help="pixel-flow sampler steps")
    ap.add_argument("--policy", default=None, help="exported Image2Nav policy folder (model.source)")
    ap.add_argument("--policy-config", default="tiny", help="navpolicy preset or config YAML")
    ap.add_argument("--observe-every", type=int, choices=(1, 2), default=2, help="steps per observation")
    ap.add_argument("--backend", default="auto", help="splatting backend (auto, cpu, torch, reference)")
    ap.add_argument("--seed", type=int, default=0, help="procedural house and start poses")
    ap.add_argument(
        "--house-preset",
        choices=("tiny", "default"),
        default="tiny",
        help="procedural house preset ('default': the size of the sim2real pipeline's houses)",
    )
    ap.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a shared box)")
    ap.add_argument(
        "--device",
        default="cpu",
        help="where the Gaussian rows render (cpu, cuda); the exact renderer and the policy stay on the "
        "CPU. A non-CPU run writes reports/rollout_throughput_<device>.*",
    )
    ap.add_argument("--quick", action="store_true", help="smoke run: defaults B in {1, 2}, 4 steps, 1 repeat")
    args = ap.parse_args(argv)
    defaults = ([1, 2], 4, 1) if args.quick else ([1, 4], 32, 5)
    for name, value in zip(("batch", "steps", "repeats"), defaults, strict=True):
        if getattr(args, name) is None:
            setattr(args, name, value)
    rows, meta, lines = run(
        batches=args.batch,
        steps=args.steps,
        repeats=args.repeats,
        obs=args.obs,
        rows=sorted(set(args.rows) | {REFERENCE}),
        renderer=args.renderer,
        flow_steps=args.flow_steps,
        policy=args.policy,
        policy_config=args.policy_config,
        observe_every=args.observe_every,
        seed=args.seed,
        threads=args.threads,
        backend=args.backend,
        house_preset=args.house_preset,
        device=args.device,
    )
    name = NAME if args.device == "cpu" else f"{NAME}_{args.device.replace(':', '')}"
    json_path, _ = write_report(name, rows, meta, markdown=lines, reports=reports)
    print("\n".join(lines))
    return {**meta, "rows": rows, "path": str(json_path)}


if __name__ == "__main__":
    main()
