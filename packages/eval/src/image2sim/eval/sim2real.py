"""The sim-to-real experiment's numbers: transfer rows, the gap, the data-scaling curve, the budget.

Policies trained on observations of one source (``neural``: the pixel-flow renderer over Gaussian
scenes built from captures; ``splat_only``: the same Gaussians without the learned renderer;
``exact``: the procedural houses rendered exactly, an upper bound) are evaluated on held-out houses
with the exact renderer (``eval nav --backend exact``), beside the ``random`` and ``forward``
baselines. Each evaluation writes the usual ``nav.json`` document; this module gathers them:

``metrics/sim2real.json``::

    {"format": "image2sim-sim2real", "version": 1, "protocol": {...},
     "rows": {"neural": {"sr", "sr_ci", "spl", "spl_ci", "ndtw", "ne", "episodes"}, ...},   # SR etc. in %
     "gap": {"sr": exact - neural, ...},
     "scaling": [{"episodes" (training), "houses", "sr", "sr_ci", "spl", "ndtw", "eval_episodes"}, ...],
     "policies": {"neural": "<path relative to the repo root>", ...},
     "budget": {...}, "checks": {...},
     "by_start_distance": {"bins": [...], "rows": {row: [{"sr", "sr_ci", "episodes"}, ...]}},  # --episodes
     "training_seeds": {row: {"seeds": {label: {"sr", "sr_ci", "episodes", "paired"?}}, "mean_sr",
                              "min_sr", "max_sr", "sd_sr", "pooled_sr_ci", ...}},  # --seed-run
     "gap_over_seeds": {"sr": exact mean - neural mean, "neural_seeds", "exact_seeds"}}  # both seeded

A check compares the policy with each baseline twice: by the issue's bar on the marginal 95 %
intervals, and pair by pair on the same episodes (``checks.*.paired``: the SR difference with
Newcombe's paired interval and the exact McNemar p-value) where both evaluations' per-episode logs
are at hand (:func:`episode_successes`).

:func:`gather` is pure (documents in, document out); :mod:`image2sim.eval.sim2real_report` renders
and writes its JSON, Markdown report and scaling plot.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "ROWS",
    "episode_successes",
    "gather",
    "instruction_check",
    "row_from_nav",
    "scaling_trend",
    "sr_by_start_distance",
    "training_seeds",
]

ROWS = ("neural", "splat_only", "exact", "random", "forward")
"""Rows of the transfer table: the three training sources and the two baselines."""
TRAINED = ("neural", "splat_only", "exact")
START_DISTANCE_EDGES = (3.0, 4.0, 6.0, 10.0)
"""Bins of the start's geodesic distance to the goal (m) for the SR breakdown: the success distance
is 3 m, so an episode of the first bin starts within 1 m of success; the last bin is open above."""
BASELINES = ("random", "forward")


def _pct(v: Any) -> float | None:
    return None if v is None else 100.0 * float(v)


def row_from_nav(doc: Mapping[str, Any], agent: str, where: str = "nav.json") -> dict:
    """One row (percentages) from a ``nav.json`` document's ``agents[agent]``."""
    agents = doc.get("agents") or {}
    if agent not in agents:
        raise ValueError(f"{where}: no agent {agent!r} (has {sorted(agents)})")
    a = agents[agent]
    return {
        "sr": _pct(a["sr"]),
        "sr_ci": [_pct(x) for x in a["sr_ci"]],
        "spl": _pct(a["spl"]),
        "spl_ci": [_pct(x) for x in a.get("spl_ci") or [None, None]],  # None: no SPL (no path lengths)
        "ndtw": _pct(a.get("ndtw")),
        "ne": a.get("ne"),
        "steps": a.get("steps"),
        "episodes": int(a["n_episodes"]),
        # how the episodes end (percent; nav_summary.OUTCOMES), None for evaluations made before it
        "outcomes": {k: _pct(v) for k, v in a["outcomes"].items()} if a.get("outcomes") else None,
    }


def scaling_trend(points: Sequence[Mapping[str, Any]]) -> dict:
    """How SR moves along the scaling points (sorted by episodes): first and last point, the change,
    whether their 95 % intervals are disjoint, and whether SR never falls from one point to the next."""
    pts = sorted(points, key=lambda p: p["episodes"])
    if len(pts) < 2:
        return {"points": len(pts), "direction": "n/a"}
    first, last = pts[0], pts[-1]
    delta = last["sr"] - first["sr"]
    disjoint = last["sr_ci"][0] > first["sr_ci"][1] or first["sr_ci"][0] > last["sr_ci"][1]
    if disjoint:
        direction = "rises" if delta > 0 else "falls"
    else:
        direction = "flat within the intervals"
    return {
        "points": len(pts),
        "episodes_span": last["episodes"] / max(first["episodes"], 1),
        "sr_change": delta,
        "first_last_disjoint": bool(disjoint),
        "monotone_non_decreasing": all(b["sr"] >= a["sr"] for a, b in zip(pts, pts[1:], strict=False)),
        "direction": direction,
    }


def gather(
    rows: Mapping[str, Mapping[str, Any]],
    scaling: Sequence[Mapping[str, Any]] = (),
    policies: Mapping[str, str] | None = None,
    budget: Mapping[str, Any] | None = None,
    extra_checks: Mapping[str, Any] | None = None,
    start_distances: Mapping[str, float] | None = None,
    seed_runs: Mapping[str, Mapping[str, Mapping[str, Any]]] | None = None,
) -> dict:
    """The ``metrics/sim2real.json`` document.

    Args:
        rows: row name -> ``{"doc": nav.json document, "agent": agent name in it}``; the baselines
            are usually the ``random`` / ``forward`` agents of one document.
        scaling: ``{"episodes", "houses", "doc", "agent"}`` per point of the data-scaling curve.
        policies: row -> exported policy folder (relative to the repo root).
        budget: free-form training budget record (wall / CPU seconds, parameters, frames seen).
        extra_checks: more held-out evaluations, name -> ``{"rows": {...}}`` like ``rows``.
        start_distances: episode id -> the start's geodesic distance to the goal (m) of the held-out
            episodes; with it, ``by_start_distance`` splits the SR of every row with per-episode
            results by :data:`START_DISTANCE_EDGES`.
        seed_runs: row -> seed label -> the row's policy retrained with that training seed and
            evaluated on the same episodes (specs like ``rows``'): :func:`training_seeds`.
    """
    protocol = None
    out_rows = {}
    successes = _successes_of(rows)
    for name, spec in rows.items():
        out_rows[name] = row_from_nav(spec["doc"], spec["agent"], spec.get("where", name))
        p = spec["doc"].get("protocol")
        if protocol is None:
            protocol = p
        elif p is not None and p != protocol:
            raise ValueError(f"row {name!r} was evaluated under another protocol than the others")
    doc: dict[str, Any] = {
        "format": "image2sim-sim2real",
        "version": 1,
        "protocol": protocol,
        "rows": out_rows,
    }
    if "neural" in out_rows and "exact" in out_rows:
        n, e = out_rows["neural"], out_rows["exact"]
        doc["gap"] = {
            k: (e[k] - n[k]) if e[k] is not None and n[k] is not None else None for k in ("sr", "spl", "ndtw")
        }
    pts = []
    for p in scaling:
        r = row_from_nav(p["doc"], p["agent"], p.get("where", "scaling"))
        # "episodes" of a scaling point counts training episodes; its evaluation's count moves aside.
        pts.append(
            {**r, "eval_episodes": r["episodes"], "episodes": int(p["episodes"]), "houses": int(p["houses"])}
        )
    doc["scaling"] = sorted(pts, key=lambda q: q["episodes"])
    doc["scaling_trend"] = scaling_trend(doc["scaling"])
    doc["policies"] = dict(policies or {})
    doc["budget"] = dict(budget or {})
    doc["checks"] = {"heldout": target_check(out_rows, successes=successes)}
    if INSTRUCTION_PAIR[0] in out_rows and INSTRUCTION_PAIR[1] in out_rows:
        doc["checks"]["instruction"] = instruction_check(out_rows, successes=successes)
    if start_distances is not None and successes:
        doc["by_start_distance"] = sr_by_start_distance(successes, start_distances)
    for name, spec in (extra_checks or {}).items():
        extra = {k: row_from_nav(v["doc"], v["agent"], v.get("where", k)) for k, v in spec["rows"].items()}
        doc["checks"][name] = {**target_check(extra, successes=_successes_of(spec["rows"])), "rows": extra}
    if seed_runs:
        seeds = doc["training_seeds"] = training_seeds(out_rows, seed_runs, successes)
        if "neural" in seeds and "exact" in seeds:
            # The gap between the rows' seed means: one seed each moves it by as much as the rows'
            # own spread (docs/sim2real.md, ninth run).
            doc["gap_over_seeds"] = {
                "sr": seeds["exact"]["mean_sr"] - seeds["neural"]["mean_sr"],
                "neural_seeds": len(seeds["neural"]["seeds"]),
                "exact_seeds": len(seeds["exact"]["seeds"]),
            }
    return doc


def training_seeds(
    rows: Mapping[str, Mapping[str, Any]],
    seed_runs: Mapping[str, Mapping[str, Mapping[str, Any]]],
    successes: Mapping[str, Mapping[str, bool]] | None = None,
) -> dict:
    """A row's SR over training seeds: the same data, retrained with other seeds, evaluated on the
    same episodes. One training run of the tiny policy moves its SR by several points (docs/sim2real.md,
    eighth run), so a row's single run says little without its spread.

    ``rows``: the gathered rows (:func:`row_from_nav`); the row itself is seed ``"0"``.
    ``seed_runs``: row -> seed label -> ``{"doc", "agent", "where", "successes"}`` (as ``rows``' specs
    in :func:`gather`). Per row: every seed's SR with its Wilson interval and, where both have
    per-episode results, its paired comparison with the best baseline (:func:`target_check`'s
    choice); the mean, min, max and standard deviation of the seeds' SRs; the mean over the best
    baseline's SR; and the pooled SR (every seed's episodes together) with its Wilson interval, which
    leaves the between-seed variance out and so is read beside min and max.
    """
    from statistics import mean, stdev

    from image2sim.eval.nav_summary import wilson_interval

    base = [b for b in BASELINES if b in rows]
    best = max(base, key=lambda b: rows[b]["sr"]) if base else None
    out: dict[str, Any] = {}
    for name, runs in seed_runs.items():
        if name not in rows:
            raise ValueError(f"seed runs of {name!r}, which is not a row (rows: {sorted(rows)})")
        if "0" in runs:
            raise ValueError(f"seed runs of {name!r}: label '0' is the row itself; give the others")
        seeds: dict[str, dict] = {"0": rows[name]}
        succ = {"0": (successes or {}).get(name)}
        for label, spec in runs.items():
            r = row_from_nav(spec["doc"], spec["agent"], spec.get("where", f"{name}/{label}"))
            if r["episodes"] != rows[name]["episodes"]:
                raise ValueError(
                    f"seed run {name}/{label} ({spec.get('where', '?')}): {r['episodes']} episodes, "
                    f"row {name!r} has {rows[name]['episodes']}: not the same evaluation"
                )
            seeds[label], succ[label] = r, spec.get("successes")
        srs = [r["sr"] for r in seeds.values()]
        n = rows[name]["episodes"]
        k = sum(round(x * n / 100.0) for x in srs)
        lo, hi = wilson_interval(k, n * len(srs))
        entry: dict[str, Any] = {
            "seeds": {},
            "mean_sr": mean(srs),
            "min_sr": min(srs),
            "max_sr": max(srs),
            "sd_sr": stdev(srs) if len(srs) > 1 else None,
            "pooled_sr_ci": [_pct(lo), _pct(hi)],
            "pooled_episodes": n * len(srs),
        }
        if best is not None:
            entry["best_baseline"] = best
            entry["mean_ratio_to_best_baseline"] = _sr_ratio({"sr": entry["mean_sr"]}, rows[best])
        for label, r in seeds.items():
            one = {"sr": r["sr"], "sr_ci": r["sr_ci"], "episodes": r["episodes"]}
            if best is not None and succ[label] is not None and (successes or {}).get(best) is not None:
                one["paired"] = _paired({label: succ[label], best: successes[best]}, label, best)
            entry["seeds"][label] = one
        out[name] = entry
    return out


def _successes_of(specs: Mapping[str, Mapping[str, Any]]) -> dict[str, Mapping[str, bool]]:
    """Row -> its per-episode successes, for the rows that have them."""
    return {name: spec["successes"] for name, spec in specs.items() if spec.get("successes") is not None}


def sr_by_start_distance(
    successes: Mapping[str, Mapping[str, bool]],
    start_distances: Mapping[str, float],
    edges: Sequence[float] = START_DISTANCE_EDGES,
) -> dict:
    """SR in percent (Wilson 95 % interval) of each row per bin of the start's distance to the goal.

    ``successes``: row -> episode id -> success; ``start_distances``: episode id -> metres. Bin ``i``
    holds ``edges[i] <= d < edges[i + 1]`` (the last bin is open above); an episode nearer than
    ``edges[0]`` is an error, as is a row's episode without a distance. Returns ``{"bins": [{"low",
    "high" (None: open), "episodes"}], "rows": {row: [{"sr", "sr_ci", "episodes"} per bin]}}``;
    a bin without episodes has ``sr`` None."""
    from image2sim.eval.nav_summary import wilson_interval

    edges = [float(e) for e in edges]
    if not edges or any(b <= a for a, b in zip(edges, edges[1:], strict=False)):
        raise ValueError(f"start-distance edges must be increasing, got {edges}")

    def bin_of(episode: str) -> int:
        d = start_distances.get(episode)
        if d is None or not math.isfinite(d):
            raise ValueError(f"episode {episode!r} has no start distance in the episodes file")
        if d < edges[0]:
            raise ValueError(f"episode {episode!r} starts {d:.2f} m from its goal, below {edges[0]} m")
        return sum(d >= e for e in edges[1:])

    bins = [{"low": lo, "high": hi, "episodes": 0} for lo, hi in zip(edges, [*edges[1:], None], strict=True)]
    bin_index = {e: bin_of(e) for e in set().union(*successes.values())}  # every row's episodes, once
    for i in bin_index.values():
        bins[i]["episodes"] += 1
    rows: dict[str, list[dict]] = {}
    for name, per_episode in successes.items():
        n = [0] * len(bins)
        k = [0] * len(bins)
        for episode, ok in per_episode.items():
            n[bin_index[episode]] += 1
            k[bin_index[episode]] += bool(ok)
        rows[name] = [
            {
                "sr": 100.0 * k[i] / n[i] if n[i] else None,
                "sr_ci": [100.0 * x for x in wilson_interval(k[i], n[i])] if n[i] else None,
                "episodes": n[i],
            }
            for i in range(len(bins))
        ]
    return {"bins": bins, "rows": rows}


def _paired(successes: Mapping[str, Mapping[str, bool]], policy: str, other: str) -> dict | None:
    """The paired comparison of two rows in percent, None when either lacks per-episode results."""
    from image2sim.eval.nav_summary import paired_success_comparison

    if policy not in successes or other not in successes:
        return None
    try:
        c = paired_success_comparison(successes[policy], successes[other])
    except ValueError as exc:
        raise ValueError(f"rows {policy!r} and {other!r}: {exc}") from exc
    return {
        **c,
        "sr_difference": _pct(c["sr_difference"]),
        "difference_ci": [_pct(x) for x in c["difference_ci"]],
    }


def _sr_ratio(row: Mapping[str, Any], reference: Mapping[str, Any]) -> float | None:
    """SR of ``row`` over SR of ``reference`` (inf over a zero reference, None when both are 0)."""
    if reference["sr"] > 0:
        return row["sr"] / reference["sr"]
    return math.inf if row["sr"] > 0 else None


def target_check(
    rows: Mapping[str, Mapping[str, Any]],
    policy: str = "neural",
    successes: Mapping[str, Mapping[str, bool]] | None = None,
) -> dict:
    """Issue 19's bar: the policy's SR >= 2x the best baseline's and its lower 95 % bound above the
    best baseline's upper bound. With per-episode ``successes`` (row -> episode id -> success) it adds
    ``paired``: baseline -> the policy against it on the same episodes (informative; the bar stays the
    marginal one)."""
    base = [b for b in BASELINES if b in rows]
    if policy not in rows or not base:
        return {"met": None, "reason": "missing rows"}
    best = max(base, key=lambda b: rows[b]["sr"])
    p, b = rows[policy], rows[best]
    ratio = _sr_ratio(p, b)
    twice = p["sr"] >= 2 * b["sr"]
    separated = p["sr_ci"][0] > b["sr_ci"][1]
    out = {
        "best_baseline": best,
        "sr_ratio": ratio,
        "twice_best_baseline": bool(twice),
        "intervals_separated": bool(separated),
        "met": bool(twice and separated),
    }
    paired = {b: c for b in base if (c := _paired(successes or {}, policy, b)) is not None}
    if paired:
        out["paired"] = paired
    return out


INSTRUCTION_PAIR = ("neural_bc", "blind")
"""(policy, control) of the instruction check: the neural row's behaviour-cloning policy and the same
BC on the same episodes with every trajectory told another one's instruction."""


def instruction_check(
    rows: Mapping[str, Mapping[str, Any]],
    policy: str = INSTRUCTION_PAIR[0],
    control: str = INSTRUCTION_PAIR[1],
    successes: Mapping[str, Mapping[str, bool]] | None = None,
) -> dict:
    """Does the policy gain from reading its instruction? Its SR against the instruction-blind
    control trained the same way: the difference, the ratio, and whether the 95 % intervals are
    disjoint (the only case that shows reading)."""
    p, c = rows[policy], rows[control]
    out = {
        "policy": policy,
        "control": control,
        "sr_difference": p["sr"] - c["sr"],
        "sr_ratio": _sr_ratio(p, c),
        "intervals_separated": bool(p["sr_ci"][0] > c["sr_ci"][1]),
    }
    paired = _paired(successes or {}, policy, control)
    if paired is not None:
        out["paired"] = paired
    return out


def policy_parameters(folder: str | Path) -> int | None:
    """Parameter count of an exported policy folder (its safetensors files), None when absent."""
    from safetensors import safe_open

    files = sorted(Path(folder).glob("*.safetensors"))
    if not files:
        return None
    n = 0
    for f in files:
        with safe_open(str(f), framework="np") as fh:
            for k in fh.keys():
                n += int(math.prod(fh.get_slice(k).get_shape()))
    return n


def episode_successes(
    nav_path: str | Path, agent: str, logs_dir: str | Path | None = None
) -> dict[str, bool] | None:
    """Episode id -> success of ``agent`` from the per-episode logs of the ``eval nav`` run whose
    metrics file is ``nav_path``: ``<its folder>/<agent>/*.jsonl`` (where ``eval nav --out X --metrics
    X/nav.json`` writes them), or ``logs_dir`` when the run's ``--out`` was elsewhere. None when there
    are none beside the metrics file; a ``logs_dir`` without logs, an episode logged twice (a resumed
    run) or one without a success value is an error naming the folder or log."""
    from image2sim.eval.results import episode_logs, read_episode_log

    folder = Path(logs_dir) if logs_dir is not None else Path(nav_path).parent / agent
    logs = episode_logs(folder)
    if not logs:
        if logs_dir is not None:
            raise ValueError(f"{folder}: no per-episode logs (*.jsonl) of an eval nav run")
        return None
    out: dict[str, bool] = {}
    for log in logs:
        for r in read_episode_log(log)[1]:
            s = r.metrics.get("success")
            if s is None:
                raise ValueError(f"{log}: episode {r.episode_id!r} has no success value")
            if r.episode_id in out:
                raise ValueError(f"{log}: episode {r.episode_id!r} is logged twice")
            out[r.episode_id] = bool(s >= 0.5)
    return out


def load_json(path: str | Path) -> dict:
    """A JSON document; a metrics file is joined with its ``.protocol.json`` (``read_metrics_file``).
    ``FileNotFoundError`` / ``ValueError`` name the file."""
    from image2sim.eval.results import read_metrics_file

    return read_metrics_file(path)
