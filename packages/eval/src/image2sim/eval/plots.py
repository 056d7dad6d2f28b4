"""Plots for reports and DVC: speed against error of the rendering methods (PNG, matplotlib Agg).

:func:`speed_points` extracts ``(method, steps, fps, psnr)`` from a ``metrics/render.json`` document
(pure, testable); :func:`plot_speed_vs_error` draws FPS (log x) against PSNR, one marker per method,
the pixel-flow step counts joined by a line and labelled, and writes the PNG atomically.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["SpeedPoint", "plot_speed_vs_error", "save_figure_atomic", "speed_points"]

_FLOW = re.compile(r"^flow_(\d+)step$")


@dataclass(frozen=True)
class SpeedPoint:
    """One method's operating point."""

    method: str
    """Method name in render.json."""
    steps: int | None
    """Pixel-flow steps (None for splat-only and ablations)."""
    fps: float
    """Frames per second (median after warm-up)."""
    psnr: float
    """Mean PSNR in dB."""


def speed_points(doc: Mapping[str, Any], metric: str = "psnr") -> list[SpeedPoint]:
    """Methods of a render.json document with finite FPS and ``metric``; flow methods sorted by steps.

    A method without FPS or with the metric n/a is skipped (it cannot be placed on the plot); a
    document without ``methods`` is an error.
    """
    methods = doc.get("methods")
    if not isinstance(methods, Mapping) or not methods:
        raise ValueError("render metrics document has no 'methods'")
    pts = []
    for name, rec in methods.items():
        fps, val = rec.get("fps"), rec.get(metric)
        if fps is None or val is None or not (math.isfinite(fps) and math.isfinite(val)) or fps <= 0:
            continue
        m = _FLOW.match(name)
        pts.append(SpeedPoint(name, int(m.group(1)) if m else None, float(fps), float(val)))
    return sorted(pts, key=lambda p: (p.steps is None, p.steps or 0, p.method))


def plot_speed_vs_error(
    doc: Mapping[str, Any], out_png: str | Path, metric: str = "psnr", title: str | None = None
) -> Path:
    """Write the FPS-vs-``metric`` scatter of a render.json document to ``out_png`` (atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = speed_points(doc, metric)
    if not pts:
        raise ValueError(f"no method has both fps and {metric}: nothing to plot")
    fig, ax = plt.subplots(figsize=(6.0, 4.0), dpi=120)
    flow = [p for p in pts if p.steps is not None]
    if flow:
        ax.plot([p.fps for p in flow], [p.psnr for p in flow], "-o", color="tab:blue", label="pixel flow")
        for p in flow:
            ax.annotate(
                f"{p.steps} step{'s' if p.steps > 1 else ''}",
                (p.fps, p.psnr),
                textcoords="offset points",
                xytext=(4, 4),
                fontsize=8,
            )
    others = [p for p in pts if p.steps is None]
    markers = iter("s^vD<>pP*X")
    colors = iter(["tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink", "tab:gray"])
    for p in others:
        ax.plot(
            [p.fps],
            [p.psnr],
            next(markers, "o"),
            color=next(colors, "black"),
            label=p.method.replace("_", " "),
        )
    ax.set_xscale("log")
    ax.set_xlabel("frames per second (log scale)")
    ax.set_ylabel(f"{metric.upper()} (dB)" if metric == "psnr" else metric)
    proto = doc.get("protocol", {}) if isinstance(doc.get("protocol"), Mapping) else {}
    res = proto.get("resolution")
    sub = f" at {res[0]}x{res[1]}" if isinstance(res, (list, tuple)) and len(res) == 2 else ""
    ax.set_title(title or f"Speed vs {metric.upper()}{sub}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    try:
        return save_figure_atomic(fig, out_png)
    finally:
        plt.close(fig)


def save_figure_atomic(fig: Any, out_png: str | Path) -> Path:
    """Save a matplotlib figure as PNG via a temporary file and a rename (never a half-written PNG)."""
    from image2sim.simulator.io.atomic import atomic_path

    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, format="png")
    return Path(out_png)
