"""Serving latency: the streaming Image2Nav agent in-process vs behind ``image2sim nav serve`` (HTTP).

The tiny from-scratch policy (seed 0) answers S concurrent sessions (S in {1, 4}), each streaming its
own synthetic episode of ``--steps`` 64x64 observations:

* ``in-process``: S :class:`~image2sim.navpolicy.agent.Image2NavAgent` s sharing one policy, each driven
  by its own thread; model calls take one lock, as in the server -- the reference;
* ``http``: ``image2sim nav serve --model tiny --threads 1`` in a subprocess on 127.0.0.1, S client
  threads, each with its own :class:`~image2sim.navpolicy.client.PolicyClient` and session (PNG over
  multipart; decoding, validation and JSON included).

Per-step latency is the wall time of one ``act`` / one ``POST .../step`` as its caller sees it (with S
sessions it includes waiting for the model lock); steps/s = all sessions' steps / wall time of the run.
One warm-up run per setting, then ``--repeats`` runs with the settings timed round-robin (a change in the
shared machine's load hits all of them alike); the reported p50 / p95 / steps/s are medians over those
runs, and the ratios compare HTTP with in-process at the same S, measured in the same run. The HTTP
actions are checked to equal the in-process ones (the report is refused otherwise).
Writes ``reports/serving.json`` and ``.md``. Run: ``.venv/bin/python benchmarks/serving.py``.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import threading
import time

import numpy as np
import torch
from harness import hardware, load_average, write_report
from image2sim.navpolicy.agent import Image2NavAgent
from image2sim.navpolicy.client import PolicyClient
from image2sim.navpolicy.config import tiny_config
from image2sim.navpolicy.data import synthetic_trajectories
from image2sim.navpolicy.model import build_policy

NAME = "serving"
INSTRUCTION = "walk to the white wall and stop"


def _threads(n: int, work) -> float:
    """Run ``work(i)`` for i < n in n threads; wall seconds until all finish."""
    errors: list[BaseException] = []

    def run(i):
        try:
            work(i)
        except BaseException as exc:  # re-raised in the caller
            errors.append(exc)

    ts = [threading.Thread(target=run, args=(i,)) for i in range(n)]
    t0 = time.perf_counter()
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    wall = time.perf_counter() - t0
    if errors:
        raise errors[0]
    return wall


def in_process(policy, cfg, episodes, n: int):
    """One run with ``n`` sessions: (latencies s, wall s, actions per session)."""
    lock = threading.Lock()
    lat: list[list[float]] = [[] for _ in range(n)]
    acts: list[list] = [[] for _ in range(n)]

    def work(i):
        agent = Image2NavAgent(policy, cfg.agent, cfg.system_prompt)
        agent.reset(INSTRUCTION, seed=0)
        for f in episodes[i]:
            t0 = time.perf_counter()
            with lock:
                a = agent.act(f)
            lat[i].append(time.perf_counter() - t0)
            acts[i].append([x.name for x in a])

    wall = _threads(n, work)
    return [x for li in lat for x in li], wall, acts


def over_http(url: str, episodes, n: int):
    """One run with ``n`` sessions through the server: (latencies s, wall s, actions per session)."""
    lat: list[list[float]] = [[] for _ in range(n)]
    acts: list[list] = [[] for _ in range(n)]
    clients = [PolicyClient(url) for _ in range(n)]
    sessions = [c.create_session(INSTRUCTION) for c in clients]

    def work(i):
        for f in episodes[i]:
            t0 = time.perf_counter()
            r = clients[i].step(sessions[i], f)
            lat[i].append(time.perf_counter() - t0)
            acts[i].append([x.name for x in r.actions])

    wall = _threads(n, work)
    for c, s in zip(clients, sessions, strict=True):
        c.close_session(s)
        c.close()
    return [x for li in lat for x in li], wall, acts


def start_server() -> tuple[subprocess.Popen, str]:
    """``image2sim nav serve`` on an ephemeral loopback port; returns the process and its URL."""
    cmd = [sys.executable, "-c", "from image2sim.simulator.cli import main; main()"]
    cmd += ["nav", "serve", "--model", "tiny", "--port", "0", "--threads", "1", "--max-sessions", "8"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    line = proc.stdout.readline()
    if "http://" not in line:
        proc.kill()
        raise SystemExit(f"the server did not start: {line!r}")
    url = line.split(" on ", 1)[1].split()[0]
    deadline = time.monotonic() + 60
    while True:
        try:
            with PolicyClient(url, timeout_s=2) as c:
                c.health()
            return proc, url
        except Exception:
            if time.monotonic() > deadline or proc.poll() is not None:
                proc.kill()
                raise SystemExit("the server did not answer /healthz") from None
            time.sleep(0.2)


def summary(runs: list[tuple[list[float], float, list]]) -> dict:
    """Medians over runs of p50 / p95 latency (ms) and steps/s."""
    p50 = [1000 * float(np.percentile(lat, 50)) for lat, _, _ in runs]
    p95 = [1000 * float(np.percentile(lat, 95)) for lat, _, _ in runs]
    sps = [len(lat) / wall for lat, wall, _ in runs]
    return {
        "p50_ms": statistics.median(p50),
        "p95_ms": statistics.median(p95),
        "steps_per_s": statistics.median(sps),
        "runs_p50_ms": p50,
        "runs_steps_per_s": sps,
    }


def main(steps: int = 48, repeats: int = 5, sessions=(1, 4)) -> dict:
    torch.set_num_threads(1)  # tiny models: one thread beats two contended ones (the server: --threads 1)
    cfg = tiny_config()
    policy = build_policy(cfg, seed=0)  # the server's tiny policy: same seed, same weights
    policy.model.eval()
    trajs = synthetic_trajectories(max(sessions), steps, steps, seed=5)
    episodes = [t.frames[:steps] for t in trajs]
    load_before = load_average()
    t_start = time.perf_counter()
    proc, url = start_server()
    try:
        settings = [(kind, n) for n in sessions for kind in ("in-process", "http")]

        def once(kind, n):
            if kind == "in-process":
                return in_process(policy, cfg, episodes, n)
            return over_http(url, episodes, n)

        warm = {s: once(*s) for s in settings}
        for n in sessions:
            if warm[("http", n)][2] != warm[("in-process", n)][2]:
                raise SystemExit(f"{n} session(s): HTTP actions differ from in-process: refusing to report")
        runs: dict = {s: [] for s in settings}
        for _ in range(repeats):
            for s in settings:
                res = once(*s)
                if res[2] != warm[s][2]:
                    raise SystemExit(f"{s}: actions changed between runs: refusing to report")
                runs[s].append(res)
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    elapsed = time.perf_counter() - t_start
    rows = []
    for kind, n in settings:
        s = summary(runs[(kind, n)])
        ref = summary(runs[("in-process", n)])
        rows.append(
            {
                "mode": kind,
                "sessions": n,
                "steps_per_session": steps,
                "p50_ms": s["p50_ms"],
                "p95_ms": s["p95_ms"],
                "steps_per_s": s["steps_per_s"],
                "p50_ratio_vs_in_process": s["p50_ms"] / ref["p50_ms"],
                "throughput_ratio_vs_in_process": s["steps_per_s"] / ref["steps_per_s"],
                "runs_p50_ms": s["runs_p50_ms"],
                "runs_steps_per_s": s["runs_steps_per_s"],
            }
        )
    params = sum(p.numel() for p in policy.model.parameters())
    meta = {
        "hardware": hardware(),
        "model": f"tiny Qwen3-VL from scratch (seed 0), {params} parameters, "
        f"{cfg.observation.height}x{cfg.observation.width} observations",
        "transport": "PNG over multipart/form-data, HTTP/1.1 keep-alive, "
        "uvicorn on 127.0.0.1 in a subprocess",
        "statistic": f"median over {repeats} runs (round-robin) after one warm-up run per setting",
        "actions_equal_in_process": True,
        "load_average_1min_before": load_before,
        "load_average_1min_after": load_average(),
        "seconds_total": elapsed,
    }
    md = [
        f"# {NAME}",
        "",
        f"Hardware: {meta['hardware']}  ",
        f"Model: {meta['model']}  ",
        f"Transport: {meta['transport']}.  ",
        f"Each session streams {steps} observations; {meta['statistic']}. Latency is per step as the "
        "caller sees it (with 4 sessions it includes waiting for the one model lock). The HTTP actions "
        "equal the in-process agent's for every session. 1-min load average "
        f"{load_before:.2f} before, {meta['load_average_1min_after']:.2f} after (shared machine).",
        "",
        "| mode | sessions | p50 ms | p95 ms | steps/s | p50 vs in-process | steps/s vs in-process |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        md.append(
            f"| {r['mode']} | {r['sessions']} | {r['p50_ms']:.1f} | {r['p95_ms']:.1f} | "
            f"{r['steps_per_s']:.1f} | {r['p50_ratio_vs_in_process']:.2f}x | "
            f"{r['throughput_ratio_vs_in_process']:.2f}x |"
        )
    write_report(NAME, rows, meta, markdown=md)
    print("\n".join(md))
    return {**meta, "rows": rows}


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=48, help="observations per session")
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per setting (after one warm-up)")
    args = ap.parse_args()
    main(args.steps, args.repeats)
