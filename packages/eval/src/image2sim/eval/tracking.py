"""Optional W&B logging of headline evaluation metrics (offline unless the user configures otherwise).

:func:`flatten_metrics` turns ``metrics/nav.json`` / ``metrics/render.json`` into flat scalar keys
(``nav/<agent>/<metric>``, ``render/<method>/<metric>``; pure, testable). :func:`log_metrics_wandb`
writes them to a W&B run together with the protocol, the git commit, the DVC stage, the params
profile and the resolved configuration (the command's settings and the stage's section of
``params.yaml``). wandb is imported only here; ``WANDB_MODE`` defaults to ``offline`` so nothing
leaves the machine unless the user asks for it. Artifacts and checkpoints are never logged (DVC owns
them). :func:`read_offline_run` reads an offline run's ``.wandb`` log back (wandb ships no reader).
"""

from __future__ import annotations

import math
import os
import struct
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from image2sim.simulator.tracking import git_commit, run_metadata

__all__ = ["flatten_metrics", "git_commit", "log_metrics_wandb", "read_offline_run", "run_metadata"]


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


def log_metrics_wandb(
    doc: Mapping[str, Any],
    kind: str,
    *,
    project: str = "image2sim-eval",
    stage: str | None = None,
    profile: str | None = None,
    config: Mapping[str, Any] | None = None,
    params_file: str | Path = "params.yaml",
    directory: str | Path | None = None,
) -> Path:
    """Log a metrics document to one W&B run (offline by default); returns the run's local directory.

    The run's config holds the protocol and :func:`run_metadata` (``config`` is the command's
    resolved settings). Only scalars are logged: no artifact, no checkpoint, no code snapshot.
    """
    try:
        import wandb
    except ImportError as exc:  # optional dependency
        raise RuntimeError("W&B logging needs the wandb package (pip install wandb)") from exc

    os.environ.setdefault("WANDB_MODE", "offline")
    os.environ.setdefault("WANDB_SILENT", "true")
    run_config = {
        "kind": kind,
        "protocol": doc.get("protocol"),
        **run_metadata(stage, profile, config, params_file),
    }
    run = wandb.init(
        project=project,
        job_type=f"eval_{kind}",
        config=run_config,
        dir=str(directory) if directory is not None else None,
        reinit="finish_previous",
        save_code=False,
    )
    try:
        flat = flatten_metrics(doc, kind)
        run.log(flat)
        run.summary.update(flat)
        run_dir = Path(run.dir).parent
    finally:
        run.finish()
    # finish() can return before W&B's service process has flushed the run log (an offline run file
    # was seen holding only its 7-byte header): shutting the service down flushes and closes it.
    wandb.teardown()
    return run_dir


_WANDB_BLOCK = 32768
_WANDB_HEADER = b":W&B"


def read_offline_run(run_dir: str | Path) -> list[tuple[str, Any]]:
    """The records of an offline run's ``run-*.wandb`` log as ``(record type, protobuf message)``.

    The log is W&B's framing of LevelDB's log format: a 7-byte file header (``:W&B``, magic,
    version), then 32 KiB blocks of chunks with a 7-byte header (CRC, little-endian length, type
    1 = full, 2 = first, 3 = middle, 4 = last); each whole record is a ``wandb_internal_pb2.Record``.
    """
    from wandb.proto import wandb_internal_pb2 as pb

    files = sorted(Path(run_dir).glob("run-*.wandb"))
    if not files:
        raise FileNotFoundError(f"{run_dir}: no run-*.wandb file")
    data = files[0].read_bytes()
    if data[:4] != _WANDB_HEADER:
        raise ValueError(f"{files[0]}: not a W&B run log (header {data[:4]!r})")
    out: list[tuple[str, Any]] = []
    pos, pending = 7, b""
    while pos + 7 <= len(data):
        left = _WANDB_BLOCK - pos % _WANDB_BLOCK
        _, n, kind = struct.unpack("<IHB", data[pos : pos + 7])
        if left < 7 or kind == 0:  # block trailer / zero padding
            pos += left
            continue
        chunk = data[pos + 7 : pos + 7 + n]
        pos += 7 + n
        if kind in (1, 2):
            pending = chunk
        elif kind in (3, 4):
            pending += chunk
        else:
            raise ValueError(f"{files[0]}: bad chunk type {kind} at byte {pos - 7 - n}")
        if kind in (1, 4):
            rec = pb.Record()
            rec.ParseFromString(pending)
            name = rec.WhichOneof("record_type")
            out.append((name, getattr(rec, name)))
            pending = b""
    return out
