"""Optional W&B logging of headline evaluation metrics (offline unless the user configures otherwise).

:func:`flatten_metrics` turns ``metrics/nav.json`` / ``metrics/render.json`` into flat scalar keys
(``nav/<agent>/<metric>``, ``render/<method>/<metric>``; pure, testable). :func:`log_metrics_wandb`
writes them to a W&B run together with the protocol, the git commit, the DVC stage and the params
profile. wandb is imported only here; ``WANDB_MODE`` defaults to ``offline`` so nothing leaves the
machine unless the user asks for it. Artifacts are never uploaded (DVC owns them).
"""

from __future__ import annotations

import math
import os
import subprocess
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["flatten_metrics", "git_commit", "log_metrics_wandb"]


def flatten_metrics(doc: Mapping[str, Any], kind: str) -> dict[str, float]:
    """Finite scalar metrics of a nav (``kind="nav"``) or render (``kind="render"``) document.

    Confidence intervals become ``..._low`` / ``..._high``; ``None`` (n/a) and non-finite values are
    left out rather than logged as 0.
    """
    section = {"nav": "agents", "render": "methods"}.get(kind)
    if section is None:
        raise ValueError(f"kind must be 'nav' or 'render', got {kind!r}")
    groups = doc.get(section)
    if not isinstance(groups, Mapping):
        raise ValueError(f"{kind} metrics document has no {section!r} mapping")
    out: dict[str, float] = {}
    for name, rec in groups.items():
        for key, value in rec.items():
            if isinstance(value, bool):
                continue
            if isinstance(value, (int, float)) and math.isfinite(value):
                out[f"{kind}/{name}/{key}"] = float(value)
            elif key.endswith("_ci") and isinstance(value, (list, tuple)) and len(value) == 2:
                out[f"{kind}/{name}/{key}_low"] = float(value[0])
                out[f"{kind}/{name}/{key}_high"] = float(value[1])
    return out


def git_commit(cwd: str | Path | None = None) -> str | None:
    """The current git commit (short), or None outside a repository."""
    try:
        res = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=cwd,
            capture_output=True,
            text=True,
            timeout=10,
            check=False,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return res.stdout.strip() or None


def log_metrics_wandb(
    doc: Mapping[str, Any],
    kind: str,
    *,
    project: str = "image2sim-eval",
    stage: str | None = None,
    profile: str | None = None,
    directory: str | Path | None = None,
) -> Path:
    """Log a metrics document to one W&B run (offline by default); returns the run's local directory."""
    try:
        import wandb
    except ImportError as exc:  # optional dependency
        raise RuntimeError("W&B logging needs the wandb package (pip install wandb)") from exc

    os.environ.setdefault("WANDB_MODE", "offline")
    os.environ.setdefault("WANDB_SILENT", "true")
    config = {
        "kind": kind,
        "protocol": doc.get("protocol"),
        "git_commit": git_commit(),
        "dvc_stage": stage or os.environ.get("DVC_STAGE"),
        "params_profile": profile or os.environ.get("IMAGE2SIM_PROFILE"),
    }
    run = wandb.init(
        project=project,
        job_type=f"eval_{kind}",
        config=config,
        dir=str(directory) if directory is not None else None,
        reinit="finish_previous",
    )
    try:
        flat = flatten_metrics(doc, kind)
        run.log(flat)
        run.summary.update(flat)
        return Path(run.dir).parent
    finally:
        run.finish()
