"""The sim-to-real report: Markdown tables and the scaling plot of a :func:`image2sim.eval.sim2real.gather`
document, and :func:`write_outputs`, which writes them with the metrics JSON, each atomically."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from image2sim.eval.sim2real import BASELINES, ROWS

__all__ = ["budget_markdown", "plot_scaling", "sim2real_markdown", "write_outputs"]


def _paired_text(c: Mapping[str, Any], policy: str, other: str) -> str:
    """One sentence of a paired comparison (percent)."""
    d = c["sr_difference"]
    lo, hi = c["difference_ci"]
    return (
        f"on the same {c['episodes']} episodes `{policy}` - `{other}` SR = {'+' if d >= 0 else ''}{d:.1f} "
        f"points [95% CI {lo:+.1f}, {hi:+.1f}]; only `{policy}` succeeded in {c['policy_only']}, only "
        f"`{other}` in {c['baseline_only']}, both in {c['both']}; exact McNemar p = {c['mcnemar_p']:.2g}"
    )


def _in_row_order(names: Mapping[str, Any]) -> list[str]:
    """The transfer table's order: :data:`ROWS` first, then the other rows as given."""
    return [r for r in ROWS if r in names] + [r for r in names if r not in ROWS]


def _fmt(v: Any, nd: int = 1) -> str:
    return "n/a" if v is None else f"{v:.{nd}f}"


def _ci(c: Sequence[Any]) -> str:
    return "n/a" if not c or c[0] is None else f"[{c[0]:.1f}, {c[1]:.1f}]"


def sim2real_markdown(doc: Mapping[str, Any], plot_name: str | None = None) -> str:
    """The report's tables (rows, gap, scaling, checks) from a :func:`gather` document."""
    lines = [
        "| policy / baseline | SR % [95% CI] | SPL % [95% CI] | nDTW % | NE (m) | steps | episodes "
        "| passed the goal % | stopped short % |"
    ]
    lines.append("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for name in _in_row_order(doc["rows"]):
        r = doc["rows"][name]
        o = r.get("outcomes") or {}
        lines.append(
            f"| {name} | {_fmt(r['sr'])} {_ci(r['sr_ci'])} | {_fmt(r['spl'])} {_ci(r['spl_ci'])} | "
            f"{_fmt(r['ndtw'])} | {_fmt(r['ne'], 2)} | {_fmt(r['steps'])} | {r['episodes']} | "
            f"{_fmt(o.get('passed_goal'))} | {_fmt(o.get('stopped_short'))} |"
        )
    out = ["## Transfer to held-out houses (exact renderer)", "", *lines, ""]
    out += [
        "Passed the goal: came within the success distance but ended elsewhere; stopped short: never "
        "came within it and stopped (n/a: evaluated before outcomes were recorded).",
        "",
    ]
    if doc.get("gap"):
        g = doc["gap"]
        out += [
            f"Sim-to-real gap (`exact` - `neural`): SR {_fmt(g['sr'])} points, SPL {_fmt(g['spl'])}, "
            f"nDTW {_fmt(g['ndtw'])}.",
            "",
        ]
    for name, chk in doc.get("checks", {}).items():
        if name == "instruction":
            diff = chk["sr_difference"]
            verdict = (
                "disjoint: the policy reads its instruction"
                if chk["intervals_separated"]
                else "overlap: no measurable instruction following"
            )
            out.append(
                f"Check `instruction`: `{chk['policy']}` SR - `{chk['control']}` SR (the same BC with "
                f"shuffled instructions) = {'+' if diff >= 0 else ''}{_fmt(diff)} points; "
                f"intervals {verdict}."
                + (
                    f" Paired: {_paired_text(chk['paired'], chk['policy'], chk['control'])}."
                    if chk.get("paired")
                    else ""
                )
            )
            out.append("")
            continue
        if chk.get("met") is None:
            continue
        rows = chk.get("rows")  # another evaluation's rows (e.g. fresh seeds): say what they scored
        scored = (
            " ("
            + ", ".join(f"{k} {_fmt(r['sr'])} {_ci(r['sr_ci'])}" for k, r in rows.items())
            + f"; {next(iter(rows.values()))['episodes']} episodes)"
            if rows
            else ""
        )
        out.append(
            f"Check `{name}`{scored}: neural SR / best baseline ({chk['best_baseline']}) = "
            f"{_fmt(chk['sr_ratio'], 2)}x; "
            f">= 2x: {'yes' if chk['twice_best_baseline'] else 'no'}; lower bound above the baseline's "
            f"upper bound: {'yes' if chk['intervals_separated'] else 'no'} -> target "
            f"{'met' if chk['met'] else 'not met'}."
        )
        for base, c in (chk.get("paired") or {}).items():
            out.append(f"- paired (`{name}`): {_paired_text(c, 'neural', base)}.")
        out.append("")
    out += _start_distance_markdown(doc.get("by_start_distance"))
    out += _seeds_markdown(doc.get("training_seeds"))
    if doc.get("gap_over_seeds"):
        g = doc["gap_over_seeds"]
        out += [
            f"Sim-to-real gap over training seeds (`exact` mean of {g['exact_seeds']} - `neural` mean of "
            f"{g['neural_seeds']}): SR {_fmt(g['sr'])} points.",
            "",
        ]
    if doc.get("scaling"):
        out += ["## Data scaling (neural simulator data, behaviour cloning only)", ""]
        out += [
            "| training houses | episodes | SR % [95% CI] | SPL % | nDTW % |",
            "|---:|---:|---|---:|---:|",
        ]
        for p in doc["scaling"]:
            out.append(
                f"| {p['houses']} | {p['episodes']} | {_fmt(p['sr'])} {_ci(p['sr_ci'])} | "
                f"{_fmt(p['spl'])} | {_fmt(p['ndtw'])} |"
            )
        t = doc.get("scaling_trend", {})
        if t.get("points", 0) >= 2:
            out += [
                "",
                f"Trend over {t['points']} points spanning {t['episodes_span']:.0f}x in episodes: SR "
                f"{'+' if t['sr_change'] >= 0 else ''}{t['sr_change']:.1f} points from the smallest to the "
                f"largest set; {t['direction']} (first and last 95 % intervals "
                f"{'disjoint' if t['first_last_disjoint'] else 'overlap'}; "
                f"{'never falls' if t['monotone_non_decreasing'] else 'not monotone'} between points).",
            ]
        if plot_name:
            out += ["", f"![SR against training episodes]({plot_name})"]
        out.append("")
    out += budget_markdown(doc.get("budget") or {})
    return "\n".join(out)


def _seeds_markdown(seeds: Mapping[str, Any] | None) -> list[str]:
    """The training-seeds table of :func:`training_seeds` (nothing without one)."""
    if not seeds:
        return []
    best = next((e["best_baseline"] for e in seeds.values() if e.get("best_baseline")), None)
    vs = f"paired - `{best}`" if best else "paired"
    out = [
        "## Training seeds (the same data and episodes, other training seeds)",
        "",
        f"| row | seed | SR % [95% CI] | {vs}: points [95% CI], McNemar p |",
        "|---|---|---|---|",
    ]
    for name, e in seeds.items():
        for label, r in e["seeds"].items():
            c = r.get("paired")
            pair = (
                f"{c['sr_difference']:+.1f} [{c['difference_ci'][0]:+.1f}, {c['difference_ci'][1]:+.1f}], "
                f"p {c['mcnemar_p']:.2g}"
                if c
                else "n/a"
            )
            out.append(f"| {name} | {label} | {_fmt(r['sr'])} {_ci(r['sr_ci'])} | {pair} |")
    out.append("")
    for name, e in seeds.items():
        ratio = e.get("mean_ratio_to_best_baseline")
        sd = "" if e["sd_sr"] is None else f", sd {e['sd_sr']:.1f}"
        out.append(
            f"- `{name}` over {len(e['seeds'])} seeds: mean SR {_fmt(e['mean_sr'])} "
            f"(min {_fmt(e['min_sr'])}, max {_fmt(e['max_sr'])}{sd})"
            + (f", {_fmt(ratio, 2)}x the best baseline (`{e['best_baseline']}`)" if ratio is not None else "")
            + f"; pooled over {e['pooled_episodes']} episode runs {_ci(e['pooled_sr_ci'])} (this interval "
            "leaves out the between-seed variance: read it beside min and max)."
        )
    out.append("")
    return out


def _start_distance_markdown(split: Mapping[str, Any] | None) -> list[str]:
    """The SR-by-start-distance table of :func:`sr_by_start_distance` (nothing without one)."""
    if not split or not split.get("rows"):
        return []
    bins = split["bins"]
    head = [f"{b['low']:g}-{b['high']:g} m" if b["high"] is not None else f">= {b['low']:g} m" for b in bins]
    out = [
        "## SR by the start's distance to the goal (geodesic)",
        "",
        "| row | " + " | ".join(head) + " |",
        "|---|" + "---:|" * len(bins),
        "| episodes | " + " | ".join(str(b["episodes"]) for b in bins) + " |",
    ]
    for name in _in_row_order(split["rows"]):
        cells = [_fmt(c["sr"]) for c in split["rows"][name]]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    out += [
        "",
        "SR in % per bin (rows with per-episode logs). The nearest bin starts just outside the success "
        "distance, where a short walk in a plausible direction succeeds; the far bins show navigation.",
        "",
    ]
    return out


def budget_markdown(budget: Mapping[str, Any]) -> list[str]:
    """The budget section: measured wall / CPU time per stage, policy sizes, data per source."""
    if not budget:
        return []
    out = ["## Budget (measured by the pipeline)", ""]
    timed = {k: v for k, v in budget.items() if isinstance(v, Mapping) and "wall_s" in v}
    if timed:
        out += ["| stage | wall (min) | CPU (min) |", "|---|---:|---:|"]
        for k, v in sorted(timed.items()):
            out.append(f"| {k} | {v['wall_s'] / 60:.1f} | {v['cpu_s'] / 60:.1f} |")
        total = sum(v["wall_s"] for v in timed.values())
        out += [
            f"| total of the timed stages | {total / 60:.1f} | |",
            "",
            "CPU time counts the command's own process tree; Ray workers (the data engine's "
            "episodes stages) run outside it, so their CPU is not included there.",
            "",
        ]
    params = {
        k[len("policy_") :]: v["parameters"]
        for k, v in budget.items()
        if k.startswith("policy_") and isinstance(v, Mapping) and v.get("parameters")
    }
    if params:
        out.append("Policy parameters: " + ", ".join(f"{k} {v:,}" for k, v in sorted(params.items())) + ".")
        out.append("")
    data = budget.get("data")
    if isinstance(data, Mapping) and data:
        out += [
            "| source | generated episodes | stored frames | DAgger episodes | DAgger frames "
            "| BC samples seen | DAgger samples seen |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for k, v in data.items():
            out.append(
                f"| {k} | {v['generated_episodes']} | {v['generated_frames']} | {v['dagger_episodes']} | "
                f"{v['dagger_frames']} | {v['bc_samples_seen']} | {v['dagger_samples_seen']} |"
            )
        out += ["", "A sample is one trajectory with up to 16 observations and 32 action labels.", ""]
    return out


def plot_scaling(doc: Mapping[str, Any], path: str | Path) -> Path:
    """SR with 95 % intervals against training episodes (log x, ticked at the points), the baselines'
    intervals as bands and the trained rows as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from image2sim.eval.plots import save_figure_atomic
    from matplotlib.ticker import FixedLocator, NullFormatter, NullLocator

    pts = doc["scaling"]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    x = [p["episodes"] for p in pts]
    y = [p["sr"] for p in pts]
    err = [[p["sr"] - p["sr_ci"][0] for p in pts], [p["sr_ci"][1] - p["sr"] for p in pts]]
    ax.errorbar(x, y, yerr=err, marker="o", capsize=3, color="tab:blue", label="neural-sim data, BC only")
    for p in pts:
        ax.annotate(
            f"{p['houses']} house{'s' if p['houses'] != 1 else ''}",
            (p["episodes"], p["sr"]),
            textcoords="offset points",
            xytext=(5, -12),
            fontsize=7,
        )
    labels = {"neural": "neural, BC + DAgger", "exact": "exact, BC + DAgger"}
    colours = {"random": "tab:gray", "forward": "tab:orange", "neural": "tab:green", "exact": "tab:purple"}
    for name in ("random", "forward", "neural", "exact"):
        r = doc["rows"].get(name)
        if r is None:
            continue
        if name in BASELINES:  # the bands say what chance-level policies reach
            ax.axhspan(r["sr_ci"][0], r["sr_ci"][1], color=colours[name], alpha=0.12)
        ax.axhline(
            r["sr"], color=colours[name], lw=1, ls="--", label=f"{labels.get(name, name)} ({r['sr']:.1f})"
        )
    ax.set_xscale("log")
    ax.xaxis.set_major_locator(FixedLocator(sorted(set(x))))
    ax.xaxis.set_minor_locator(NullLocator())
    ax.xaxis.set_minor_formatter(NullFormatter())
    ax.set_xticklabels([str(v) for v in sorted(set(x))])
    ax.set_xlim(min(x) / 1.4, max(x) * 1.4)
    ax.set_xlabel("training episodes (neural simulator)")
    ax.set_ylabel("SR on held-out houses (%)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    out = save_figure_atomic(fig, path)
    plt.close(fig)
    return out


def write_outputs(
    doc: Mapping[str, Any], metrics: str | Path, report: str | Path, plot: str | Path | None
) -> None:
    """``metrics`` (JSON: numbers only, the rest in its ``.protocol.json``), ``report`` (Markdown) and
    the scaling ``plot`` (PNG), each atomically."""
    from image2sim.eval.results import write_metrics_file
    from image2sim.simulator.io.atomic import write_text_atomic

    metrics, report = Path(metrics), Path(report)
    metrics.parent.mkdir(parents=True, exist_ok=True)
    write_metrics_file(metrics, doc)
    name = None
    if plot is not None and doc.get("scaling"):
        plot = Path(plot)
        plot.parent.mkdir(parents=True, exist_ok=True)
        plot_scaling(doc, plot)
        try:
            name = str(plot.resolve().relative_to(report.resolve().parent))
        except ValueError:
            name = "../" + plot.as_posix() if not plot.is_absolute() else str(plot)
    report.parent.mkdir(parents=True, exist_ok=True)
    head = doc.get("header", "")
    write_text_atomic(report, (head + "\n" if head else "") + sim2real_markdown(doc, name))
