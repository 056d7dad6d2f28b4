"""Reports: Markdown tables laid out like the paper's Table 2 (navigation) and Table 1 (rendering).

Every mean is printed with its protocol, and with its episode count whenever fewer episodes than the
row's total entered it (metrics that are n/a for some episodes), so no episode disappears silently.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from image2sim.eval.metrics.nav import AggregateReport, MetricSummary
from image2sim.eval.protocols import Protocol
from image2sim.eval.render_scores import RenderCell
from image2sim.eval.results import read_result_file, write_aggregate, write_json_atomic
from image2sim.simulator.io.atomic import write_text_atomic


@dataclass(frozen=True)
class Column:
    """One table column."""

    metric: str
    """Metric key in the aggregate."""
    header: str
    """Column header (with the better direction)."""
    scale: float
    """Multiplier for display (100 for rates shown in percent)."""
    digits: int
    """Decimals shown."""


NAV_COLUMNS: tuple[Column, ...] = (
    Column("distance_to_goal", "NE↓", 1.0, 2),
    Column("oracle_success", "OSR↑", 100.0, 1),
    Column("success", "SR↑", 100.0, 1),
    Column("spl", "SPL↑", 100.0, 1),
    Column("ndtw", "nDTW↑", 100.0, 1),
    Column("sdtw", "sDTW↑", 100.0, 1),
    Column("path_length", "TL", 1.0, 2),
    Column("steps", "Steps", 1.0, 1),
)
"""The paper's Table 2 metrics (NE, OSR, SR, SPL, nDTW) plus sDTW, trajectory length and steps."""


def format_cell(summary: MetricSummary | None, total: int, column: Column) -> str:
    """``62.1``; ``n/a`` when absent; ``70.5 (n=98)`` when fewer than ``total`` episodes entered it."""
    if summary is None or summary.mean is None:
        return "n/a"
    value = f"{summary.mean * column.scale:.{column.digits}f}"
    return value if summary.count == total else f"{value} (n={summary.count})"


def nav_table_markdown(
    rows: Sequence[tuple[str, AggregateReport]], columns: Sequence[Column] = NAV_COLUMNS
) -> str:
    """A Markdown table with one row per ``(label, report)``; rates in percent, distances in metres."""
    header = ["", *[c.header for c in columns], "Episodes", "Protocol"]
    lines = ["| " + " | ".join(header) + " |", "|---" + "|---:" * (len(header) - 2) + "|---|"]
    for label, report in rows:
        cells = [format_cell(report.metrics.get(c.metric), report.num_episodes, c) for c in columns]
        row = [label, *cells, str(report.num_episodes), report.protocol.name]
        lines.append("| " + " | ".join(row) + " |")
    protocols = dict.fromkeys(r.protocol for _, r in rows)  # ordered, exact-value distinct
    notes = [f"- `{p.name}`: {describe_protocol(p)}" for p in protocols]
    return "\n".join(lines) + "\n\nProtocols:\n" + "\n".join(notes) + "\n"


def describe_protocol(p: Protocol) -> str:
    """One-line human summary of a protocol."""
    cam = p.camera
    return (
        f"{p.max_steps} steps, {p.turn_angle_deg:g}° turns, {p.forward_step_m:g} m forward, "
        f"{cam.width}×{cam.height} {cam.kind} at {cam.hfov_deg:g}° HFOV, "
        f"sliding {'on' if p.allow_sliding else 'off'}, success < {p.success_distance_m:g} m, "
        f"{p.dtw} DTW"
    )


def dvc_metrics(report: AggregateReport) -> dict[str, Any]:
    """Flat ``metrics.json`` for DVC: means (None for n/a), counts and the protocol name."""
    out: dict[str, Any] = {"protocol": report.protocol.name, "num_episodes": report.num_episodes}
    for name, s in report.metrics.items():
        out[name] = None if s.mean is None or not math.isfinite(s.mean) else s.mean
        out[f"{name}_count"] = s.count
        out[f"{name}_sem"] = s.sem
    return out


def write_nav_report(
    out_dir: str | Path, label: str, report: AggregateReport, extra: Mapping[str, Any] | None = None
) -> dict[str, Path]:
    """Write ``aggregate.json`` (result file with protocol), ``metrics.json`` (DVC) and ``table.md``."""
    out = Path(out_dir)
    paths = {
        "aggregate": write_aggregate(out / "aggregate.json", report, {"label": label, **(extra or {})}),
        "metrics": write_json_atomic(out / "metrics.json", dvc_metrics(report)),
    }
    paths["table"] = write_text_atomic(out / "table.md", nav_table_markdown([(label, report)]))
    return paths


def read_aggregate(path: str | Path) -> tuple[str, AggregateReport]:
    """Read an ``aggregate.json`` written by :func:`write_nav_report` back into ``(label, report)``."""
    protocol, payload = read_result_file(path)
    try:
        metrics = {
            k: MetricSummary(
                None if v["mean"] is None else float(v["mean"]),
                int(v["count"]),
                int(v["missing"]),
                None if v.get("sem") is None else float(v["sem"]),
            )
            for k, v in payload["metrics"].items()
        }
        report = AggregateReport(protocol, int(payload["num_episodes"]), metrics)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: not an aggregate result ({type(exc).__name__}: {exc})") from exc
    return str(payload.get("label", Path(path).parent.name)), report


RENDER_COLUMNS: tuple[Column, ...] = (
    Column("lpips", "LPIPS↓", 1.0, 3),
    Column("psnr", "PSNR↑", 1.0, 2),
    Column("ssim", "SSIM↑", 1.0, 3),
)
"""The paper's Table 1 image metrics (FPS is appended per setting)."""


def render_table_markdown(
    rows: Sequence[tuple[str, Mapping[str, RenderCell]]],
    settings: Sequence[str],
    columns: Sequence[Column] = RENDER_COLUMNS,
) -> str:
    """Table-1 layout: one row per method, a LPIPS / PSNR / SSIM / FPS group per setting (noise tier).

    LPIPS without configured weights prints ``n/a``; a missing setting prints ``–`` in its group; a
    mean over fewer views than the cell's total shows ``(n=…)``.
    """
    header = [""]
    for s in settings:
        header += [f"{c.header} ({s})" for c in columns] + [f"FPS↑ ({s})"]
    lines = ["| " + " | ".join(header) + " |", "|---" + "|---:" * (len(header) - 1) + "|"]
    hardware: set[str] = set()
    for label, cells in rows:
        out = [label]
        for s in settings:
            cell = cells.get(s)
            if cell is None:
                out += ["–"] * (len(columns) + 1)
                continue
            out += [format_cell(cell.metrics.get(c.metric), cell.num_views, c) for c in columns]
            out.append("n/a" if cell.fps is None else f"{cell.fps:.1f}")
            if cell.hardware:
                hardware.add(cell.hardware)
        lines.append("| " + " | ".join(out) + " |")
    text = "\n".join(lines) + "\n"
    if hardware:
        text += "\nFPS hardware: " + "; ".join(sorted(hardware)) + "\n"
    return text
