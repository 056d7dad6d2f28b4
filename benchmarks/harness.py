"""The one benchmark harness: hardware string, median-after-warm-up timing, atomic JSON + Markdown reports.

Every script in ``benchmarks/`` imports from here instead of carrying its own copies::

    from harness import hardware, time_it, write_report

    t = time_it(lambda: work(), warmup=1, repeats=5)      # t.wall / t.cpu: medians in seconds
    write_report("my_bench", rows, {"statistic": "median wall time, 1 warm-up"}, markdown=lines)

The timing loop itself is :func:`image2sim.eval.metrics.timing.time_calls` (shared with the
evaluation's FPS measurement), so there is exactly one implementation of "warm up, then time".
"""

from __future__ import annotations

import json
import os
import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from image2sim.eval.metrics.timing import hardware_string, time_calls
from image2sim.simulator.io.atomic import write_text_atomic

__all__ = [
    "REPORTS",
    "Timing",
    "hardware",
    "load_average",
    "time_it",
    "utc_now",
    "write_report",
    "write_text_atomic",
]

REPORTS = Path(os.environ.get("IMAGE2SIM_BENCH_REPORTS") or Path(__file__).resolve().parents[1] / "reports")
"""Where reports go: ``<repo>/reports/<name>.json`` and ``.md``; ``IMAGE2SIM_BENCH_REPORTS`` redirects
them (smoke runs that must not overwrite the committed figures)."""


def hardware() -> str:
    """CPU model, logical cores, python/torch versions and torch threads (read at call time)."""
    return hardware_string()


def load_average() -> float:
    """1-minute load average (NaN where the OS has none): how contended the shared machine was."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def utc_now() -> str:
    """ISO-8601 UTC timestamp (seconds) for report headers."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


@dataclass(frozen=True)
class Timing:
    """Result of :func:`time_it`: medians plus every timed sample (warm-up runs excluded)."""

    wall: float
    """Median wall-clock seconds per call."""
    cpu: float
    """Median process CPU seconds per call (all threads; > wall means parallel work)."""
    walls: tuple[float, ...]
    """Wall seconds of every timed call."""
    cpus: tuple[float, ...]
    """CPU seconds of every timed call."""
    warmup: int
    """Untimed calls made first."""

    @property
    def repeats(self) -> int:
        """Number of timed calls."""
        return len(self.walls)


def time_it(
    fn: Callable[[], Any],
    *,
    warmup: int = 1,
    repeats: int = 5,
    synchronize: Callable[[], None] | None = None,
) -> Timing:
    """Run ``fn`` ``warmup`` times untimed, then ``repeats`` times timed; medians of wall and CPU time."""
    walls, cpus = time_calls(fn, warmup=warmup, runs=repeats, synchronize=synchronize)
    return Timing(statistics.median(walls), statistics.median(cpus), tuple(walls), tuple(cpus), warmup)


def _cell(value: Any) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def _table(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """A Markdown table of ``rows`` with the union of their keys as columns (first-seen order)."""
    columns: list[str] = []
    for row in rows:
        columns += [k for k in row if k not in columns and not isinstance(row[k], (dict, list))]
    if not columns:
        return []
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cell(row.get(c)) for c in columns) + " |" for row in rows]
    return lines


def write_report(
    name: str,
    rows: Sequence[Mapping[str, Any]],
    meta: Mapping[str, Any] | None = None,
    *,
    markdown: Sequence[str] | str | None = None,
    title: str | None = None,
    reports: str | os.PathLike | None = None,
    rows_key: str = "rows",
) -> tuple[Path, Path]:
    """Write ``reports/<name>.json`` and ``reports/<name>.md`` atomically; returns both paths.

    The JSON is ``{"benchmark": name, "hardware": ..., "date_utc": ..., **meta, rows_key: rows}``
    (``hardware`` and ``date_utc`` are filled in unless ``meta`` gives them). The Markdown is
    ``markdown`` when given (the script's own table and notes), else a title, the hardware line and
    a table of ``rows``.
    """
    folder = Path(reports) if reports is not None else REPORTS
    report: dict[str, Any] = {"benchmark": name, "hardware": None, "date_utc": None, **(meta or {})}
    report["hardware"] = report["hardware"] or hardware()
    report["date_utc"] = report["date_utc"] or utc_now()
    report[rows_key] = [dict(r) for r in rows]
    if markdown is None:
        lines = [f"# {title or name}", "", f"Hardware: {report['hardware']}  "]
        lines.append(f"Measured {report['date_utc']}.")
        lines += ["", *_table(rows)]
        markdown = lines
    text = markdown if isinstance(markdown, str) else "\n".join(markdown)
    json_path = write_text_atomic(folder / f"{name}.json", json.dumps(report, indent=2) + "\n")
    md_path = write_text_atomic(folder / f"{name}.md", text.rstrip("\n") + "\n")
    return json_path, md_path
