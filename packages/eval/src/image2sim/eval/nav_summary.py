"""Headline numbers of a navigation run: ``metrics/nav.json`` records with 95 % intervals (Wilson for
SR, percentile bootstrap for SPL) and their Markdown table (habitat-lab's *benchmark* summary)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from image2sim.eval.metrics.nav import (
    EpisodeResult,
    aggregate,
)
from image2sim.eval.nav_env import RunnerError
from image2sim.eval.protocols import Protocol
from image2sim.eval.results import read_result_file, result_document, write_metrics_file

__all__ = [
    "OUTCOMES",
    "bootstrap_ci",
    "episode_outcomes",
    "nav_markdown",
    "mcnemar_exact_p",
    "nav_summary",
    "paired_success_comparison",
    "update_nav_metrics",
    "wilson_interval",
]


# ------------------------------------------------------------------------------------------ summaries


def wilson_interval(successes: float, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (95 % by default); (0, 1) for n = 0."""
    if n <= 0:
        return (0.0, 1.0)
    p = successes / n
    denom = 1.0 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    # At p = 0 / p = 1 the bound is exactly 0 / 1; rounding would put it a hair inside.
    lo = 0.0 if successes <= 0 else max(0.0, centre - half)
    hi = 1.0 if successes >= n else min(1.0, centre + half)
    return (lo, hi)


def bootstrap_ci(
    values: Sequence[float], n_boot: int = 2000, seed: int = 0, level: float = 0.95
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean (seeded, so it is reproducible)."""
    x = np.asarray(values, dtype=np.float64)
    if len(x) == 0:
        raise ValueError("bootstrap_ci: no values")
    if not np.all(np.isfinite(x)):
        raise ValueError("bootstrap_ci: non-finite values")
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(x), size=(n_boot, len(x)))
    means = x[idx].mean(axis=1)
    a = (1.0 - level) / 2.0
    return (float(np.quantile(means, a)), float(np.quantile(means, 1.0 - a)))


def mcnemar_exact_p(policy_only: int, baseline_only: int) -> float:
    """Two-sided exact McNemar test: the probability, if the two agents were equally good, of discordant
    episodes at least this lopsided (a binomial(n, 1/2) tail on the n discordant pairs; 1 when n = 0)."""
    b, c = int(policy_only), int(baseline_only)
    if b < 0 or c < 0:
        raise ValueError(f"mcnemar_exact_p: counts must be >= 0, got {b}, {c}")
    n = b + c
    if n == 0:
        return 1.0
    tail = sum(math.comb(n, k) for k in range(min(b, c) + 1))
    return min(1.0, 2.0 * tail / 2.0**n)


def paired_success_comparison(
    policy: Mapping[str, bool], baseline: Mapping[str, bool], z: float = 1.959963984540054
) -> dict[str, Any]:
    """Two agents' success on the *same* episodes (episode id -> success), compared pair by pair.

    Two marginal 95 % intervals that touch can still hide a clear difference: most of each agent's
    variance is which episodes are easy, which a paired comparison cancels. Returns the 2x2 counts,
    the SR difference (policy - baseline, fractions), its 95 % interval by Newcombe's hybrid score
    method for paired proportions (Stat. Med. 1998, method 10: the two Wilson intervals joined
    through the phi correlation of the pairs) and the exact McNemar p-value.
    """
    if set(policy) != set(baseline):
        only_p = sorted(set(policy) - set(baseline))[:3]
        only_b = sorted(set(baseline) - set(policy))[:3]
        raise ValueError(
            f"paired comparison needs the same episodes: {len(set(policy) ^ set(baseline))} differ "
            f"(only the policy's e.g. {only_p}, only the baseline's e.g. {only_b})"
        )
    n = len(policy)
    if n == 0:
        raise ValueError("paired comparison: no episodes")
    both = sum(1 for e, s in policy.items() if s and baseline[e])
    p_only = sum(1 for e, s in policy.items() if s and not baseline[e])
    b_only = sum(1 for e, s in policy.items() if not s and baseline[e])
    neither = n - both - p_only - b_only
    p1, p2 = (both + p_only) / n, (both + b_only) / n
    l1, u1 = wilson_interval(both + p_only, n, z)
    l2, u2 = wilson_interval(both + b_only, n, z)
    denom = (both + p_only) * (neither + b_only) * (both + b_only) * (neither + p_only)
    phi = (both * neither - p_only * b_only) / math.sqrt(denom) if denom > 0 else 0.0
    delta = p1 - p2
    # max(0, .): the radicand is a sum of squares minus a correlation term, >= 0 up to rounding
    lower = math.sqrt(max(0.0, (p1 - l1) ** 2 - 2 * phi * (p1 - l1) * (u2 - p2) + (u2 - p2) ** 2))
    upper = math.sqrt(max(0.0, (u1 - p1) ** 2 - 2 * phi * (u1 - p1) * (p2 - l2) + (p2 - l2) ** 2))
    return {
        "episodes": n,
        "both": both,
        "policy_only": p_only,
        "baseline_only": b_only,
        "neither": neither,
        "sr_difference": delta,
        "difference_ci": [max(-1.0, delta - lower), min(1.0, delta + upper)],
        "mcnemar_p": mcnemar_exact_p(p_only, b_only),
        "method": "Newcombe hybrid score interval for paired proportions (95%); exact McNemar test",
    }


OUTCOMES = ("success", "passed_goal", "stopped_short", "out_of_steps")
"""How an episode ends: within the success distance; came within it at some point but ended
elsewhere; never came within it and stopped before the step limit; never came within it and ran out
of steps. Where failures sit tells what to fix: a policy that mostly stops short needs to travel and
search, one that passes the goal needs to recognise it."""


def episode_outcomes(results: Sequence[EpisodeResult]) -> dict[str, float] | None:
    """Fraction of the goal-bearing episodes in each of :data:`OUTCOMES` (None without any)."""
    counts = dict.fromkeys(OUTCOMES, 0)
    for r in results:
        m = r.metrics
        if m.get("success") is None or m.get("oracle_success") is None:
            continue
        if m["success"]:
            counts["success"] += 1
        elif m["oracle_success"]:
            counts["passed_goal"] += 1
        elif (m.get("steps") or 0) >= r.protocol.max_steps:
            counts["out_of_steps"] += 1
        else:
            counts["stopped_short"] += 1
    n = sum(counts.values())
    return {k: v / n for k, v in counts.items()} if n else None


def nav_summary(results: Sequence[EpisodeResult], ci_seed: int = 0) -> dict[str, Any]:
    """Headline record of one agent for ``metrics/nav.json``.

    ``sr``, ``spl``, ``ne``, ``osr``, ``ndtw`` (None when no episode has a reference path), ``sdtw``,
    ``path_length``, ``steps``, ``n_episodes``, ``sr_ci`` (Wilson 95 %), ``spl_ci`` (bootstrap 95 %)
    and ``outcomes`` (:func:`episode_outcomes`).
    On episodes without a goal (a test split) every goal metric and interval is None (n/a), never 0.
    """
    report = aggregate(results)
    m = report.metrics

    def mean(k: str) -> float | None:
        s = m.get(k)
        return None if s is None or s.mean is None else float(s.mean)

    # Episodes without a goal (test splits) have no success or SPL: their intervals are n/a (None).
    sr_vals = [float(r.metrics["success"]) for r in results if r.metrics.get("success") is not None]
    spl_vals = [float(r.metrics["spl"]) for r in results if r.metrics.get("spl") is not None]
    return {
        "sr": mean("success"),
        "spl": mean("spl"),
        "ne": mean("distance_to_goal"),
        "osr": mean("oracle_success"),
        "ndtw": mean("ndtw"),
        "sdtw": mean("sdtw"),
        "path_length": mean("path_length"),
        "steps": mean("steps"),
        "n_episodes": report.num_episodes,
        "ne_approximate": mean("ne_approximate"),
        "sr_ci": list(wilson_interval(sum(sr_vals), len(sr_vals))) if sr_vals else None,
        "spl_ci": list(bootstrap_ci(spl_vals, seed=ci_seed)) if spl_vals else None,
        "outcomes": episode_outcomes(results),
        "ci_method": {"sr_ci": "wilson 95%", "spl_ci": "percentile bootstrap 95%, 2000 resamples"},
    }


def update_nav_metrics(path: str | Path, protocol: Protocol, agent: str, summary: Mapping[str, Any]) -> Path:
    """Insert/replace one agent's summary in ``metrics/nav.json`` (atomic; same protocol enforced).

    The file holds the numbers only; the protocol and the format header are in ``nav.protocol.json``
    beside it (:func:`~image2sim.eval.results.write_metrics_file`)."""
    from image2sim.eval.protocols import ProtocolMismatchError

    path = Path(path)
    agents: dict[str, Any] = {}
    if path.is_file():
        existing, payload = read_result_file(path)
        if existing != protocol:
            raise ProtocolMismatchError(
                f"{path}: holds results of protocol {existing.name!r}; refusing to add {agent!r} under "
                f"{protocol.name!r} (write to another file)"
            )
        agents = dict(payload.get("agents", {}))
    agents[agent] = dict(summary)
    return write_metrics_file(path, result_document(protocol, {"agents": agents}, path))


def nav_markdown(doc: Mapping[str, Any]) -> str:
    """Table-2 layout of a nav.json document: one row per agent, rates in percent with 95 % CIs."""
    agents = doc.get("agents") or {}
    if not agents:
        raise RunnerError("navigation metrics document has no 'agents'")

    def pct(v: Any) -> str:
        return "n/a" if v is None else f"{100 * v:.1f}"

    def ci(v: Any) -> str:
        return "" if not v else f" [{100 * v[0]:.1f}, {100 * v[1]:.1f}]"

    lines = [
        "| Agent | NE↓ | OSR↑ | SR↑ (95% CI) | SPL↑ (95% CI) | nDTW↑ | Episodes |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, a in agents.items():
        ne = "n/a" if a.get("ne") is None else f"{a['ne']:.2f}"
        lines.append(
            f"| {name} | {ne} | {pct(a.get('osr'))} | {pct(a.get('sr'))}{ci(a.get('sr_ci'))} | "
            f"{pct(a.get('spl'))}{ci(a.get('spl_ci'))} | {pct(a.get('ndtw'))} | {a.get('n_episodes')} |"
        )
    proto = doc.get("protocol") or {}
    text = "\n".join(lines) + "\n"
    outcomes = {n: a["outcomes"] for n, a in agents.items() if a.get("outcomes")}
    if outcomes:
        head = " | ".join(f"{k} %" for k in OUTCOMES)
        text += f"\n| Agent | {head} |\n|---|" + "---:|" * len(OUTCOMES)
        for n, o in outcomes.items():
            text += f"\n| {n} | " + " | ".join(f"{100 * o[k]:.1f}" for k in OUTCOMES) + " |"
        text += (
            "\n\nOutcomes: ended within the success distance; passed within it but ended elsewhere; "
            "never within it, stopped; never within it, out of steps.\n"
        )
    approx = {n: a["ne_approximate"] for n, a in agents.items() if a.get("ne_approximate")}
    if approx:
        shares = ", ".join(f"{n} {100 * v:.1f}%" for n, v in approx.items())
        text += (
            f"\nEpisodes ending where the navigation graph does not reach the goal ({shares}) use the "
            "planner's estimate (nearest goal-connected node + straight offset) for NE and success.\n"
        )
    no_goal = [n for n, a in agents.items() if a.get("sr") is None and a.get("n_episodes")]
    if no_goal:
        text += (
            f"\nNE, OSR, SR and SPL are n/a for {', '.join(no_goal)}: the episodes have no goal (a test "
            "split); the leaderboard scores the submission.\n"
        )
    if proto:
        from image2sim.eval.report import describe_protocol

        p = Protocol.from_dict(proto)
        text += f"\nProtocol `{p.name}`: {describe_protocol(p)}\n"
    return text
